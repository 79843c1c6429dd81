"""viewer stage."""

from __future__ import annotations

from splattwin._lazy import lazy_exports

# Lazy: nothing is imported until a name is used (`splattwin --help` imports the options modules only).
_EXPORTS = {"serve": "app", "TwinView": "splattwin.playback.view_model"}

__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
