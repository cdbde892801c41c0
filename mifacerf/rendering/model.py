"""The model folder opened for rendering: the format's reader plus what rendering needs of it.

The on-disk format (layout, version, reader, writer) is :mod:`mifacerf.formats.model`;
:class:`Model` adds the §5 blend model, the compressed fields and the spread
visibility of the camera weights' primary tier, each loaded or computed on first use.
"""
from __future__ import annotations

from functools import cached_property

import numpy as np

from ..formats.model import ModelError, ModelFolder


class Model(ModelFolder):
    """A model folder opened for rendering. Fields load lazily (an LRU of ``cache_bytes``)."""

    _blend = None

    @cached_property
    def visible_near(self) -> np.ndarray:
        """(S, C, T) bool: every source's visibility spread over the triangles round each vertex
        (:func:`.chunks.seen_near`; the primary tier of the camera weights), computed once."""
        from .chunks import seen_near

        return np.stack([seen_near(v, self.triangles) for v in self.visible])

    def compressed_field(self, s: int, c: int, rank: int, method: str) -> dict:
        """The ``<method><rank>`` version of a field (:mod:`.compression`), its arrays by name (cached);
        for ``pca``: {coeff (N, K) f16, basis (K, L, 3), mean (L, 3)}."""
        from .compression import compressed_path

        key = (method, rank, s, c)
        if key in self._fields:
            self._fields.move_to_end(key)
            return self._fields[key]
        path = compressed_path(self.root, self.expressions[s], self.cameras[c].name, rank, method)
        if not path.exists():
            raise ModelError(f"{path}: missing; compress the model first "
                             f"(mifacerf compress MODEL --method {method} --rank {rank})")
        self.check_file(path)
        z = np.load(path)
        comp = {k: z[k] for k in z.files}
        self.loaded_fields.append((self.expressions[s], self.cameras[c].name))
        self._fields[key] = comp
        return comp

    @property
    def blend(self):
        """The §5 blend model (loaded on first use)."""
        if self._blend is None:
            from ..blending import BlendModel

            path = self.root / "blend.npz"
            if not path.exists():
                raise ModelError(f"{path}: missing")
            self.check_file(path)
            self._blend = BlendModel.load(path)
        return self._blend
