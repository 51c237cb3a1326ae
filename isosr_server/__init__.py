"""isosr_server: `isosr serve`, the remote visualization and frame upscaling service (floor 3).

One stage per module: ``protocol`` (the wire protocol, shared with clients: numpy, msgpack and
the standard library only), ``volumes`` (names -> volumes), ``engine`` (the one thread that owns
the device), ``pipeline`` (the view modes), ``channels`` (the channel view's false colors),
``encoding`` (PNG/JPEG/WebP), ``sessions`` (latest-frame-wins view sessions with flow control, upscale sessions),
``metrics`` (Prometheus), ``core.config`` (``Settings``, the one typed settings object), ``api``
(typed dependencies on ``app.state``, one router per resource in ``api/routes/``, the browser
viewer's page among them, its files in ``static/``), ``app`` (``create_app(settings)``, the FastAPI
app). Clients import ``isosr_server.protocol`` only.
"""
