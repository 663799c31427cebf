"""The distance CNN d(I, a) and its runtimes: the paper's net (`network`), its config and
input encoding (`net_config`), its action fusions (`tiled_fusion`, `window_fusion`, the
grid head `grid_head`), mirror averaging (`mirror`) and weights I/O (`weights_io`), the
height-map FCN (`fcn`), the image's symmetric views (`views`) and ONNX export and
inference (`onnx_export`, `onnx_runtime`).

Floor 4: imports `core`, `objects` and `geometry`; knows nothing of Drake.
"""
