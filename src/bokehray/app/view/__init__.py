"""``bokehray view``: an interactive refocus page served on 127.0.0.1 (docs/view.md).

Needs the ``view`` extra (Starlette, uvicorn); importing :mod:`bokehray` never imports this.
"""

from __future__ import annotations

from .session import RenderParams, ViewSession, parse_params
from .worker import RenderWorker, Superseded

__all__ = ["RenderParams", "RenderWorker", "Superseded", "ViewSession", "parse_params"]
