"""Where map events go: the sink protocol, the null sink and the Rerun sink.

``RerunSink`` is imported lazily (``from octolgp.sinks import RerunSink`` works), so
``import octolgp`` does not load rerun-sdk.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from octolgp.sinks.base import LeafView, MapChange, NullSink, Sink

if TYPE_CHECKING:
    from octolgp.sinks.rerun import RerunSink

__all__ = ["LeafView", "MapChange", "NullSink", "RerunSink", "Sink"]


def __getattr__(name: str) -> Any:
    if name == "RerunSink":
        from octolgp.sinks.rerun import RerunSink

        return RerunSink
    raise AttributeError(f"module 'octolgp.sinks' has no attribute {name!r}")
