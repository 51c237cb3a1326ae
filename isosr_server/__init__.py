"""isosr_server: `isosr serve`, the remote visualization and frame upscaling service (floor 3).

One stage per module: ``protocol`` (the wire protocol, shared with clients: numpy, msgspec and
the standard library only), ``codecs`` (array and buffers coding), ``volumes`` (names -> volumes),
``engine`` (the one thread that owns the device), ``pipeline`` (the view modes), ``channels``
(the channel view's false colors), ``encoding`` (PNG/JPEG/WebP), ``sessions`` (latest-frame-wins
view sessions with flow control, upscale sessions), ``metrics`` (Prometheus), ``app``
(``create_app(config)``, the FastAPI app), ``viewer`` (the browser page at ``/``, its files in
``static/``). Clients import ``isosr_server.protocol`` and ``isosr_server.codecs`` (but not its
``buffers_device``) only.
"""
