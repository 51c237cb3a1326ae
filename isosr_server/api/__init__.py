"""The HTTP and WebSocket API: typed dependencies (``deps``), one router per resource (``routes``),
error answers (``errors``), WebSocket plumbing (``ws``), all routers together (``main``)."""
