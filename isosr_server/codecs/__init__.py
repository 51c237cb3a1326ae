"""Codecs of the wire: :mod:`~isosr_server.codecs.arrays` (numpy arrays as ``{dtype, shape, data[, zlib]}``),
:mod:`~isosr_server.codecs.buffers` (the ``buffers`` view mode's coding: decode, numpy only) and
:mod:`~isosr_server.codecs.buffers_device` (its encoder, torch on the frame's device: the server's alone).

Clients import the first two only; nothing here imports torch but ``buffers_device``.
"""
