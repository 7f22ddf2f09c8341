"""Weights files as their publishers ship them, read into a state dict {name: tensor}.

- ``.safetensors`` (OpenCLIP on the Hugging Face hub): read here (8-byte header length, a JSON
  table of dtype, shape and byte range per tensor, then the bytes), no extra package;
- a ``torch.save`` zip or pickle (OpenCLIP ``.bin``/``.pt``, SAM ``sam_vit_*.pth``): loaded with
  ``weights_only=True``, unwrapped from a ``state_dict``/``model`` entry when there is one;
- a TorchScript archive (OpenAI CLIP ``ViT-B-16.pt``): its parameters and buffers.

Every failure is a :class:`FeaturesError` naming the file.
"""
from __future__ import annotations

import hashlib
import json
import os
import struct
import zipfile
from pathlib import Path

import numpy as np
import torch

from .errors import FeaturesError

#: safetensors dtype names -> (numpy dtype of the stored bytes, torch dtype).
_SAFETENSORS_DTYPES = {"F64": (np.float64, torch.float64), "F32": (np.float32, torch.float32),
                       "F16": (np.float16, torch.float16), "BF16": (np.int16, torch.bfloat16),
                       "I64": (np.int64, torch.int64), "I32": (np.int32, torch.int32),
                       "I16": (np.int16, torch.int16), "I8": (np.int8, torch.int8),
                       "U8": (np.uint8, torch.uint8), "BOOL": (np.bool_, torch.bool)}
_TORCH_TO_SAFETENSORS = {t: name for name, (_, t) in _SAFETENSORS_DTYPES.items()}


def read_safetensors(path: Path) -> dict[str, torch.Tensor]:
    """The tensors of a ``.safetensors`` file (CPU, their stored dtypes)."""
    data = path.read_bytes()
    if len(data) < 8:
        raise FeaturesError(f"{path}: not a safetensors file (only {len(data)} bytes)")
    (size,) = struct.unpack("<Q", data[:8])
    try:
        header = json.loads(data[8:8 + size])
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FeaturesError(f"{path}: not a safetensors file (header: {exc})") from None
    header.pop("__metadata__", None)
    body = memoryview(data)[8 + size:]
    tensors = {}
    for name, entry in header.items():
        try:
            np_dtype, torch_dtype = _SAFETENSORS_DTYPES[entry["dtype"]]
            begin, end = entry["data_offsets"]
            shape = tuple(entry["shape"])
        except (KeyError, TypeError, ValueError):
            raise FeaturesError(f"{path}: tensor {name!r}: malformed header entry {entry!r}") from None
        if end > len(body) or end - begin != int(np.prod(shape)) * np.dtype(np_dtype).itemsize:
            raise FeaturesError(f"{path}: tensor {name!r}: bytes {begin}..{end} do not hold a "
                                f"{entry['dtype']} {list(shape)} (file truncated?)")
        array = np.frombuffer(body[begin:end], np_dtype).reshape(shape).copy()
        tensors[name] = torch.from_numpy(array).view(torch_dtype)
    return tensors


def write_safetensors(path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str] | None = None) -> None:
    """Write ``tensors`` as a ``.safetensors`` file (the format :func:`read_safetensors` reads)."""
    header, chunks, offset = {}, [], 0
    for name, tensor in tensors.items():
        t = tensor.detach().contiguous().cpu()
        raw = t.view(torch.int16).numpy().tobytes() if t.dtype == torch.bfloat16 else t.numpy().tobytes()
        header[name] = {"dtype": _TORCH_TO_SAFETENSORS[t.dtype], "shape": list(t.shape),
                        "data_offsets": [offset, offset + len(raw)]}
        chunks.append(raw)
        offset += len(raw)
    if metadata:
        header["__metadata__"] = metadata
    blob = json.dumps(header).encode()
    blob += b" " * (-len(blob) % 8)
    with open(path, "wb") as fh:
        fh.write(struct.pack("<Q", len(blob)) + blob)
        for raw in chunks:
            fh.write(raw)


def _is_torchscript(path: Path) -> bool:
    if not zipfile.is_zipfile(path):
        return False
    with zipfile.ZipFile(path) as archive:
        return any(n.endswith("constants.pkl") or "/code/" in n for n in archive.namelist())


def _unwrap(obj, path: Path) -> dict[str, torch.Tensor]:
    for key in ("state_dict", "model"):
        if isinstance(obj, dict) and isinstance(obj.get(key), dict):
            obj = obj[key]
    if not isinstance(obj, dict) or not any(isinstance(v, torch.Tensor) for v in obj.values()):
        raise FeaturesError(f"{path}: holds no state dict of tensors ({type(obj).__name__})")
    return {str(k): v for k, v in obj.items() if isinstance(v, torch.Tensor)}


def load_state_dict(path: str | os.PathLike, option: str) -> tuple[dict[str, torch.Tensor], bool]:
    """(state dict {name: CPU tensor}, whether the file is a TorchScript archive) of the weights
    file ``path`` given by the command-line ``option`` (named in errors). FeaturesError for a
    missing, empty or unreadable file."""
    path = Path(path)
    if not path.is_file():
        raise FeaturesError(f"{path}: no such weights file ({option})")
    if path.stat().st_size == 0:
        raise FeaturesError(f"{path}: empty weights file ({option})")
    if path.suffix == ".safetensors":
        return read_safetensors(path), False
    try:
        if _is_torchscript(path):
            return {k: v for k, v in torch.jit.load(str(path), map_location="cpu").state_dict().items()}, True
        return _unwrap(torch.load(path, map_location="cpu", weights_only=True), path), False
    except FeaturesError:
        raise
    except Exception as exc:  # torch.load raises many kinds (pickle, zip, EOF, runtime) for a bad file
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise FeaturesError(f"{path}: not a readable weights file ({option}): {reason[:200]}") from None


def file_sha256(path: str | os.PathLike) -> str:
    """The hex sha256 of a file's bytes (weights files are identified by it)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def missing_keys(state: dict[str, torch.Tensor], module: torch.nn.Module) -> list[str]:
    """Names of ``module``'s parameters and persistent buffers that ``state`` lacks."""
    return [k for k in module.state_dict() if k not in state]
