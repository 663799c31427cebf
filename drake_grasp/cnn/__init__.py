"""The distance CNN d(I, a) and its runtimes: the paper's net and its grid head
(`network`), the height-map FCN (`fcn`), the image's symmetric views (`views`) and
ONNX export and inference (`onnx_export`, `onnx_runtime`).

Floor 4: imports `core`, `objects` and `geometry`; knows nothing of Drake.
"""
