"""Implementations of ``runtime.backend.ModelBackend``: ``torch_backend`` (the network of a
``.pt`` checkpoint) and ``onnx_backend`` (an ``.onnx`` export run by onnxruntime).

Nothing is imported here: each module pulls in its own framework when it is used
(``registry.create_backend`` picks one by name; ``registry`` is the one place that names
them).
"""
