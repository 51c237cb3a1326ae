"""The service's core: its settings (``config``)."""
