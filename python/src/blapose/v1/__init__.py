"""Generated protobuf and gRPC stubs for ``proto/blapose/v1/blapose.proto``.

Do not edit ``blapose_pb2*.py``: regenerate them with
``python python/tools/gen_stubs.py`` (``tests/test_stubs.py`` checks they match).
"""
