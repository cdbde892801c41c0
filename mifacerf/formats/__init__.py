"""The on-disk formats, each with its reader, writer and version (ground floor: imports no stage).

* :mod:`.files` — atomic writes, JSON documents and manifests, sha256 checksums;
* :mod:`.capture` — the capture folder (``mifacerf.capture/1``): what a light stage writes;
* :mod:`.registration` — the registration folder (``mifacerf.registration/1``): registration's output;
* :mod:`.model` — the model folder (``mifacerf.model/1``): what ``mifacerf build`` writes and rendering reads;
* :mod:`.performance` — the performance folder (``mifacerf.performance/1``): tracking's input video.

Each module's docstring documents its layout. Importing this package imports nothing heavy
(no Mitsuba): the capture reader works in a process that never renders.
"""
