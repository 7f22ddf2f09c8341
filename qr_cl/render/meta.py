"""The meta mapping the public renderers return (:func:`qr_cl.rasterize`,
:func:`qr_cl.render_volume_fused`)."""
from __future__ import annotations

from collections.abc import Mapping

from ..stages import PLAN_META_KEYS, RasterPlan


class RenderMeta(Mapping):
    """The meta of a render: :meth:`~qr_cl.stages.RasterPlan.meta`'s entries, copied to the host
    on the first access of one of them (a render whose meta is never read makes no copies), and
    the ``extra`` entries given. A read-only mapping with the keys of both."""

    def __init__(self, plan: RasterPlan, **extra) -> None:
        self._plan, self._extra, self._host = plan, extra, None

    def __getitem__(self, key: str):
        if key in self._extra:
            return self._extra[key]
        if key not in PLAN_META_KEYS:
            raise KeyError(key)
        if self._host is None:
            self._host = self._plan.meta()
        return self._host[key]

    def __iter__(self):
        return iter((*PLAN_META_KEYS, *self._extra))

    def __len__(self) -> int:
        return len(PLAN_META_KEYS) + len(self._extra)
