"""One router per resource: ``health``, ``models``, ``volumes``, ``upscale``, ``view``, ``metrics``, ``viewer``."""
