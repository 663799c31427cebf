"""The distance CNN d(I, a) and its runtimes: the paper's net (`network`: the layers, the
shared image trunk and the public forms), its config and input encoding (`net_config`),
one head per action fusion that the net delegates to (`tiled_fusion.TiledHead`, the
paper's, with the inference-only fast IP1 paths `tiled_fusion.InferenceIP1`;
`window_fusion.WindowHead`; `grid_head.GridHead`), mirror averaging (`mirror`) and
weights I/O (`weights_io`), the height-map FCN (`fcn`), the image's symmetric views
(`views`) and ONNX export and inference (`onnx_export`, `onnx_runtime`).

Floor 4: imports `core`, `objects` and `geometry`; knows nothing of Drake.
"""
