"""Weights I/O of the distance CNN, safetensors only (a weights file cannot run code):
`save_weights` writes a `drake_grasp.cnn.network.DistanceCNN`'s state dict with
self-describing metadata (`WEIGHTS_FORMAT`, the `NetworkConfig`, the code version, a
SHA-256 of the tensor data from `tensors_sha256`, and the user's metadata), atomically;
`load_weights` verifies all of it and rebuilds the net from the stored config, so a
corrupted or mismatched file fails loudly instead of loading garbage.

A file may store its tensors in half precision (`save_weights(..., storage_dtype=
torch.float16)`, `half_precision_copy`): half the bytes on disk and in the wheel. Such a
net is loaded into a float32 model (`COMPUTE_DTYPES`), so it computes in float32 with
weights rounded to float16; the file's sha256 is its identity, like any other net's.
"""

import dataclasses
import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Optional, Union

import safetensors
import safetensors.torch
import torch

import drake_grasp
from drake_grasp.cnn.net_config import NetworkConfig
from drake_grasp.core.assets import missing_weights_message
from drake_grasp.cnn.network import DistanceCNN

WEIGHTS_FORMAT = "drake_grasp.DistanceCNN/1"
"""Value of the ``format`` metadata key of a weights file written by `save_weights`."""

# Metadata keys written by `save_weights`; user metadata goes in its own JSON entry so
# it can never shadow these.
_KEY_FORMAT = "format"
_KEY_CONFIG = "config"
_KEY_CODE_VERSION = "code_version"
_KEY_TENSORS_SHA256 = "tensors_sha256"
_KEY_USER = "user_metadata"

# load_weights adds these to the returned metadata, so users may not set them.
_RESERVED_USER_KEYS = ("config", "code_version", "format", "storage_dtype")

COMPUTE_DTYPES = {torch.float16: torch.float32, torch.bfloat16: torch.float32}
"""Stored dtype -> the dtype `load_weights` builds the net in, where they differ: half
precision is a storage format here (CPU float16 arithmetic is slow and coarse)."""


def tensors_sha256(tensors: dict[str, torch.Tensor]) -> str:
    """SHA-256 over names, dtypes, shapes and raw bytes of tensors, in sorted name order.

    safetensors has no checksum, so a flipped byte inside the tensor data would load
    as different weights without this.
    """
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(f"{name}\0{t.dtype}\0{tuple(t.shape)}\0".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def save_weights(
    model: DistanceCNN, path: Union[str, os.PathLike], *, metadata: dict[str, Any],
    storage_dtype: Optional[torch.dtype] = None,
) -> None:
    """Writes the weights as a safetensors file with self-describing metadata.

    The file's metadata holds: ``format`` (`WEIGHTS_FORMAT`), ``config`` (the
    `NetworkConfig` as JSON: architecture and input normalization), ``code_version``
    (`drake_grasp.__version__`), ``tensors_sha256`` (`tensors_sha256`) and
    ``user_metadata`` (`metadata` as JSON; put e.g. ``dataset_manifest_sha256``,
    training run id, epoch there). The file is written to a temporary name in the
    same folder and renamed, so a crash never leaves a half-written file at `path`.

    Args:
        model: The network.
        path: Destination, conventionally ``*.safetensors``.
        metadata: JSON-serialisable user metadata (may be empty).
        storage_dtype: The dtype the tensors are stored in (torch.float16 halves the
            file; `load_weights` computes in float32 all the same); None keeps the
            model's own dtype.

    Raises:
        ValueError: `metadata` is not a dict or not JSON-serialisable, or
            `storage_dtype` is not a floating dtype.
    """
    if storage_dtype is not None and not storage_dtype.is_floating_point:
        raise ValueError(f"storage_dtype: expected a floating torch dtype, got {storage_dtype}")
    if not isinstance(metadata, dict):
        raise ValueError(f"metadata: expected a dict, got {type(metadata).__name__}")
    reserved = sorted(set(metadata) & set(_RESERVED_USER_KEYS))
    if reserved:
        raise ValueError(f"metadata: keys {reserved} are reserved (load_weights fills them in)")
    try:
        user_json = json.dumps(metadata, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(f"metadata: must be JSON-serialisable: {e}") from e
    tensors = {k: v.detach().cpu().to(storage_dtype or v.dtype).contiguous().clone()
               for k, v in model.state_dict().items()}
    header = {
        _KEY_FORMAT: WEIGHTS_FORMAT,
        _KEY_CONFIG: json.dumps(model.config.to_dict(), sort_keys=True),
        _KEY_CODE_VERSION: drake_grasp.__version__,
        _KEY_TENSORS_SHA256: tensors_sha256(tensors),
        _KEY_USER: user_json,
    }
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        safetensors.torch.save_file(tensors, tmp, metadata=header)
        os.chmod(tmp, 0o644)  # mkstemp makes it owner-only; weights are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_weights(
    path: Union[str, os.PathLike], *, expected_config: Optional[NetworkConfig] = None
) -> tuple[DistanceCNN, dict[str, Any]]:
    """Loads and verifies a file written by `save_weights`.

    Checks, in order: the file exists; it parses as safetensors; its metadata has the
    expected format and parses; the tensor data matches its SHA-256; the stored config
    is valid and (if given) equals `expected_config`; the tensors' names and shapes
    equal the state dict of the net that config builds. The model gets the dtype of
    the stored tensors (float32 for half-precision storage, `COMPUTE_DTYPES`) and is
    returned in eval mode.

    Args:
        path: A ``.safetensors`` file from `save_weights`.
        expected_config: If given, every field must match the stored config.

    Returns:
        (model, metadata): metadata is the user metadata given to `save_weights`,
        plus ``config`` (dict), ``code_version``, ``format`` and ``storage_dtype``
        (e.g. "float16").

    Raises:
        FileNotFoundError: No file at `path`.
        ValueError: Anything else wrong; the message names the file and the key/field.
    """
    path = Path(path)
    if not path.is_file():
        # A net the wheel does not carry is named with its folder in the repository.
        raise FileNotFoundError(missing_weights_message(path))
    try:
        with safetensors.safe_open(str(path), framework="pt") as f:
            header = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as e:  # SafetensorError, truncated buffers, bad JSON header, ...
        raise ValueError(f"{path}: not a valid safetensors file ({type(e).__name__}: {e})") from e

    for key in (_KEY_FORMAT, _KEY_CONFIG, _KEY_CODE_VERSION, _KEY_TENSORS_SHA256, _KEY_USER):
        if key not in header:
            raise ValueError(
                f"{path}: metadata key {key!r} missing (not a drake_grasp DistanceCNN "
                f"weights file? found keys {sorted(header)})"
            )
    if header[_KEY_FORMAT] != WEIGHTS_FORMAT:
        raise ValueError(
            f"{path}: metadata 'format' is {header[_KEY_FORMAT]!r}, expected {WEIGHTS_FORMAT!r}"
        )
    digest = tensors_sha256(tensors)
    if digest != header[_KEY_TENSORS_SHA256]:
        raise ValueError(
            f"{path}: tensor data does not match metadata 'tensors_sha256' (file corrupted "
            f"or modified): stored {header[_KEY_TENSORS_SHA256]}, computed {digest}"
        )
    parsed = {}
    for key in (_KEY_CONFIG, _KEY_USER):
        try:
            parsed[key] = json.loads(header[key])
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: metadata {key!r} is not valid JSON: {e}") from e
    if not isinstance(parsed[_KEY_USER], dict):
        raise ValueError(f"{path}: metadata 'user_metadata' must be a JSON object")
    config = NetworkConfig.from_dict(parsed[_KEY_CONFIG], source=f"{path}: metadata 'config'")

    if expected_config is not None:
        for field in dataclasses.fields(NetworkConfig):
            stored, wanted = getattr(config, field.name), getattr(expected_config, field.name)
            if stored != wanted:
                raise ValueError(
                    f"{path}: config field {field.name!r} is {stored!r} in the file, "
                    f"expected {wanted!r}"
                )

    dtypes = {t.dtype for t in tensors.values()}
    if len(dtypes) != 1 or not next(iter(dtypes)).is_floating_point:
        raise ValueError(
            f"{path}: expected all tensors to share one floating dtype, got "
            + ", ".join(f"{k}: {t.dtype}" for k, t in sorted(tensors.items()))
        )
    stored_dtype = next(iter(dtypes))
    model = DistanceCNN(config, dtype=COMPUTE_DTYPES.get(stored_dtype, stored_dtype))
    expected = model.state_dict()
    for key in sorted(set(expected) | set(tensors)):
        if key not in tensors:
            raise ValueError(f"{path}: tensor {key!r} missing (the stored config needs it)")
        if key not in expected:
            raise ValueError(f"{path}: unexpected tensor {key!r} (not in the stored config's net)")
        if tuple(tensors[key].shape) != tuple(expected[key].shape):
            raise ValueError(
                f"{path}: tensor {key!r} has shape {tuple(tensors[key].shape)}, the stored "
                f"config needs {tuple(expected[key].shape)}"
            )
    model.load_state_dict(tensors, strict=True)  # copies, casting to the model's dtype
    model.eval()
    metadata = dict(parsed[_KEY_USER])
    metadata.update(
        config=config.to_dict(),
        code_version=header[_KEY_CODE_VERSION],
        format=header[_KEY_FORMAT],
        storage_dtype=str(stored_dtype).removeprefix("torch."),
    )
    return model, metadata


def half_precision_copy(src: Union[str, os.PathLike], dst: Union[str, os.PathLike]) -> dict:
    """Writes `src`'s net with its tensors stored in float16 to `dst` (atomically).

    The copy keeps `src`'s config and user metadata and adds ``half_precision_of`` (the
    sha256 of `src`'s file) to the user metadata; ``code_version`` is this package's.

    Returns:
        The largest absolute change of any weight, as {"max_abs_change": float}.

    Raises:
        FileNotFoundError, ValueError: As `load_weights` for `src`; `dst` equals `src`.
    """
    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve():
        raise ValueError(f"half_precision_copy: {dst} is the source file itself")
    model, meta = load_weights(src)
    user = {k: v for k, v in meta.items() if k not in _RESERVED_USER_KEYS}
    user["half_precision_of"] = hashlib.sha256(src.read_bytes()).hexdigest()
    save_weights(model, dst, metadata=user, storage_dtype=torch.float16)
    with torch.no_grad():
        change = max(float((p - p.half().to(p.dtype)).abs().max())
                     for p in model.state_dict().values())
    return {"max_abs_change": change}
