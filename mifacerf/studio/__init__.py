"""``mifacerf studio CAPTURE``: the paper's interactive point editor and registration program (§3, §4, Fig. 4)
in the browser, with the hand work proposed automatically (docs/studio.md).

A local web server (:mod:`.server`, Starlette + uvicorn, loopback only by default, a per-launch token)
serves a single-page app (``static/``: plain HTML, JavaScript and CSS, no build step) over one capture
folder in the documented format (docs/capture-format.md). It reads the manifest, the images, the
hand inputs and the registration folder; it writes only the hand inputs (``hand/template.json``,
``hand/coarse_points.json``, ``hand/rotoscope/<expression>.json``), the registration overrides
(``hand/overrides.json``, :mod:`mifacerf.registration.overrides`) and, when asked to register, the
registration folder. It never reads a synthetic subject's ``truth/``.

Modules: :mod:`.session` (the capture, the hand documents with versions, geometry for the page),
:mod:`.images` (tone-mapped views), :mod:`.security` (paths, token, Host and Origin checks),
:mod:`.jobs` (registration in the background), :mod:`.proposals` (hand inputs proposed from the images
and from registered expressions), :mod:`.server` (routes), :mod:`.cli`.
"""
