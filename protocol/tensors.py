"""Tensors on the wire: ``{dtype, shape, data}`` with the raw bytes, never ``tolist()``.

Decoding validates dtype, shape, byte count and finiteness so a malformed or poisoned array never reaches the math.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

#: dtypes a tensor may travel as (little-endian, as numpy spells them).
ALLOWED_DTYPES = frozenset({"<f4", "<f8", "<f2", "<i4", "<i8", "|u1"})
#: No single tensor above this many elements (a 3x128 MLP has ~35k parameters).
MAX_ELEMENTS = 16_000_000
MAX_NDIM = 8
#: Largest L2 norm of an actor's gradient or parameters anyone accepts (honest ones stay below 1e3): it keeps every
#: sum the chief forms far inside float32, and an absurd aggregate or transfer away from a worker's actor.
NORM_LIMIT = 1e6


class TensorBlob(BaseModel):
    """One array as dtype string, shape and raw little-endian bytes."""

    model_config = ConfigDict(frozen=True)

    dtype: str = Field(json_schema_extra={"enum": [*sorted(ALLOWED_DTYPES)]})  # for the schema; _check checks it
    shape: tuple[int, ...] = Field(max_length=MAX_NDIM)
    data: bytes

    @model_validator(mode="after")
    def _check(self) -> TensorBlob:
        if self.dtype not in ALLOWED_DTYPES:
            raise ValueError(f"dtype {self.dtype!r} not allowed (allowed: {sorted(ALLOWED_DTYPES)})")
        if any(d < 0 for d in self.shape):
            raise ValueError(f"negative dimension in shape {self.shape}")
        count = math.prod(self.shape)  # Python integers: no overflow, whatever the shape claims
        if count > MAX_ELEMENTS:
            raise ValueError(f"tensor of {count} elements exceeds the limit of {MAX_ELEMENTS}")
        expected = count * np.dtype(self.dtype).itemsize
        if len(self.data) != expected:
            raise ValueError(f"shape {self.shape} of {self.dtype} needs {expected} bytes, got {len(self.data)}")
        if np.dtype(self.dtype).kind == "f" and not np.isfinite(self.to_array()).all():
            raise ValueError("tensor contains NaN or Inf")
        return self

    @classmethod
    def from_array(cls, array: np.ndarray) -> TensorBlob:
        """Wrap an array (converted to little-endian and contiguous)."""
        arr = np.ascontiguousarray(array)
        arr = arr.astype(arr.dtype.newbyteorder("<"), copy=False)
        return cls(dtype=arr.dtype.str, shape=tuple(int(d) for d in arr.shape), data=arr.tobytes())

    def to_array(self) -> np.ndarray:
        """A read-only view on the bytes; ``.copy()`` before changing it in place."""
        return np.frombuffer(self.data, dtype=np.dtype(self.dtype)).reshape(self.shape)


TensorDict = dict[str, TensorBlob]


def pack_arrays(arrays: Mapping[str, np.ndarray]) -> TensorDict:
    """Named arrays (e.g. an actor's parameters) to blobs."""
    return {name: TensorBlob.from_array(np.asarray(a)) for name, a in arrays.items()}


def unpack_arrays(blobs: Mapping[str, TensorBlob]) -> dict[str, np.ndarray]:
    """Blobs to writable numpy arrays."""
    return {name: blob.to_array().copy() for name, blob in blobs.items()}


def spec_of(arrays: Mapping[str, np.ndarray] | Mapping[str, TensorBlob]) -> dict[str, tuple[int, ...]]:
    """Name -> shape, to compare a message against the model it is meant for."""
    return {name: tuple(int(d) for d in a.shape) for name, a in arrays.items()}


def check_spec(arrays: Mapping[str, object], expected: Mapping[str, tuple[int, ...]], what: str) -> None:
    """Raise ValueError naming the first difference between ``arrays`` and the expected name -> shape spec."""
    got = spec_of(arrays)  # type: ignore[arg-type]
    missing = sorted(set(expected) - set(got))
    extra = sorted(set(got) - set(expected))
    if missing or extra:
        raise ValueError(f"{what}: tensor names differ (missing {missing}, unexpected {extra})")
    for name, shape in expected.items():
        if got[name] != tuple(shape):
            raise ValueError(f"{what}: {name} has shape {got[name]}, expected {tuple(shape)}")


def digest(arrays: Mapping[str, np.ndarray | TensorBlob]) -> str:
    """A short fingerprint of named tensors (names, dtypes, shapes and bytes as they travel), for receipts and
    audits: the same tensors give the same digest on the chief and on every worker."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = arrays[name]
        blob = a if isinstance(a, TensorBlob) else TensorBlob.from_array(np.asarray(a))
        h.update(f"{name}|{blob.dtype}|{blob.shape}|".encode())
        h.update(blob.data)
    return h.hexdigest()[:16]


def l2_norm(arrays: Mapping[str, np.ndarray] | Mapping[str, TensorBlob]) -> float:
    """The L2 norm over all tensors, in float64 (inf when it overflows or a value is not finite)."""
    total = 0.0
    for a in arrays.values():
        values = a.to_array() if isinstance(a, TensorBlob) else np.asarray(a)
        total += float(np.sum(np.square(values, dtype=np.float64)))
    return math.sqrt(total) if math.isfinite(total) else math.inf


def answer_digest(gradient: Mapping[str, np.ndarray] | Mapping[str, TensorBlob] | None,
                  critic: Mapping[str, np.ndarray] | Mapping[str, TensorBlob] | None = None) -> str:
    """The digest of an aggregate's tensors ('' when it shares none): its actor gradient, or with a critic gradient
    both, named ``actor/...`` and ``critic/...``."""
    if gradient is None:
        return ""
    if critic is None:
        return digest(gradient)
    return digest({**{f"actor/{k}": v for k, v in gradient.items()}, **{f"critic/{k}": v for k, v in critic.items()}})
