"""Half-precision storage of the distance CNN: stored in float16, computed in float32."""

import hashlib

import pytest
import safetensors
import torch

from drake_grasp.cnn.network import DistanceCNN
from drake_grasp.cnn.weights_io import half_precision_copy, load_weights, save_weights


def _model(seed: int = 5) -> DistanceCNN:
    return DistanceCNN(None, generator=torch.Generator().manual_seed(seed), dtype=torch.float32)


def test_float16_storage_loads_as_float32_with_rounded_weights(tmp_path):
    m = _model()
    path = tmp_path / "half.safetensors"
    save_weights(m, path, metadata={"epoch": 1}, storage_dtype=torch.float16)
    with safetensors.safe_open(str(path), framework="pt") as f:
        assert {f.get_tensor(k).dtype for k in f.keys()} == {torch.float16}
    loaded, meta = load_weights(path, expected_config=m.config)
    assert loaded.dtype == torch.float32 and meta["storage_dtype"] == "float16"
    assert meta["epoch"] == 1
    for name, p in m.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], p.half().float()), name
    # float32 weights load as they are, and say so
    full = tmp_path / "full.safetensors"
    save_weights(m, full, metadata={})
    assert load_weights(full)[1]["storage_dtype"] == "float32"


def _header(path) -> dict:
    with safetensors.safe_open(str(path), framework="pt") as f:
        return dict(f.metadata())


def test_half_precision_copy_halves_the_file_and_names_its_source(tmp_path):
    src, dst = tmp_path / "src.safetensors", tmp_path / "dst.safetensors"
    save_weights(_model(), src, metadata={"epoch": 3})
    change = half_precision_copy(src, dst)
    assert 0 < change["max_abs_change"] < 1e-3
    assert dst.stat().st_size < 0.55 * src.stat().st_size
    loaded, meta = load_weights(dst)
    assert meta["half_precision_of"] == hashlib.sha256(src.read_bytes()).hexdigest()
    assert meta["epoch"] == 3 and meta["storage_dtype"] == "float16"
    first = _header(dst)
    half_precision_copy(src, dst)  # deterministic: the same tensors and metadata again
    assert _header(dst) == first  # (safetensors orders the header's keys at random)
    with pytest.raises(ValueError, match="source file itself"):
        half_precision_copy(src, src)


def test_save_weights_rejects_a_non_floating_storage_dtype(tmp_path):
    with pytest.raises(ValueError, match="storage_dtype"):
        save_weights(_model(), tmp_path / "a.safetensors", metadata={}, storage_dtype=torch.int8)
    assert not (tmp_path / "a.safetensors").exists()
