"""isosr_server: `isosr serve`, the remote visualization and frame upscaling service (floor 3).

One stage per module: ``protocol`` (the wire protocol, shared with clients: msgspec Structs,
numpy and the standard library only), ``codecs`` (arrays, the buffers coding; its device encoder
the server's alone, KServe v2 bodies), ``volumes`` (names -> volumes), ``engine`` (the one thread
that owns the device, and the encoder thread), ``views`` (the view modes: isosr_net's frame
methods plus ``auto`` and ``focus``), ``auto`` (the auto mode's budget policy), ``channels`` (the
channel view's false colors), ``encoding`` (PNG/JPEG/WebP), ``sessions`` (latest-frame-wins view
sessions with flow control, upscale sessions), ``guard`` (what a client may hold: connections,
bodies, first messages), ``metrics`` (Prometheus), ``core.config`` (``Settings``, the one typed
settings object), ``api`` (typed dependencies on ``app.state``, one router per resource in
``api/routes/``, the browser viewer's page among them, its files in ``static/``), ``app``
(``create_app(settings)``, the FastAPI app), and past one process ``cluster``, ``placement``,
``replica`` (Ray Serve). Clients import ``isosr_server.protocol`` and ``codecs`` only.
"""
