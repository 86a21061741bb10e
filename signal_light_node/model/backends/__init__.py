"""Implementations of ``runtime.backend.ModelBackend``: ``torch_backend`` (the network of a
``.pt`` checkpoint) and ``onnx_backend`` (an ``.onnx`` export run by onnxruntime).

Nothing is imported here: each module pulls in its own framework when it is used
(``runtime.backend.create_backend`` picks one by name).
"""
