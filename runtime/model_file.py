"""A worker's saved model, read without torch: what ``--init-model PATH`` names, and the model's digest.

A model file is what a worker saves when it solves (worker/ppo.py ``state_dict`` plus its ``provenance``, written
with ``torch.save``). The chief, which has no torch, must name and compare the model a run was warm-started from,
so this module reads that file format itself: a zip archive holding ``data.pkl`` (the pickled dict, tensors as
references to storages) and one raw little-endian ``data/<key>`` entry per storage. The pickle is read with an
allow-list (plain containers and torch's tensor and storage references only), so a file cannot run code.

- ``resolve(path)``: a model file, or a run folder: the model of its first worker to solve (summary.json's
  ``workers``, the smallest solve episode, then ``models/<id>.pt``).
- ``network_digest(path)``: sha256 over the actor's and the critic's tensors (names, dtypes, shapes and bytes): the
  digest a warm-started worker's hello carries and the chief compares. It ignores everything else in the file
  (optimizer state, provenance), so a model copied or re-saved with other metadata keeps its digest.

Every problem is a ``ModelFileError`` (a ValueError): one line, exit code 2 where a process reports it.
"""

from __future__ import annotations

import hashlib
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from pydantic import AfterValidator

from runtime.records import RunSummary

#: The networks the digest covers (keys of the saved dict).
NETWORKS = ("actor", "critic")
#: torch storage classes and their element sizes and numpy-style names.
_STORAGES = {"FloatStorage": ("float32", 4), "DoubleStorage": ("float64", 8), "HalfStorage": ("float16", 2),
             "BFloat16Storage": ("bfloat16", 2), "LongStorage": ("int64", 8), "IntStorage": ("int32", 4),
             "ShortStorage": ("int16", 2), "CharStorage": ("int8", 1), "ByteStorage": ("uint8", 1),
             "BoolStorage": ("bool", 1)}


def mature_model(folder: Path, worker_id: str) -> Path:
    """Where a worker saves its model when it solves: ``<model dir>/<id>.pt`` (a run's ``models/<id>.pt``)."""
    return folder / f"{worker_id}.pt"


def last_model(folder: Path, worker_id: str) -> Path:
    """Where a worker that played its episodes without solving saves its last networks: ``<model dir>/<id>.last.pt``
    (never taken for a solver's: ``resolve`` and a warm start's choice read it only when named)."""
    return folder / f"{worker_id}.last.pt"


class ModelFileError(ValueError):
    """A model path that cannot be used: missing, unreadable, not a worker's model, or a run folder without one."""


@dataclass(frozen=True)
class StorageRef:
    """A tensor's storage in the archive: its key (``data/<key>``), dtype and element size."""

    key: str
    dtype: str
    itemsize: int


@dataclass(frozen=True)
class TensorRef:
    """A tensor as the pickle describes it (no data read yet)."""

    storage: StorageRef
    offset: int
    shape: tuple[int, ...]
    stride: tuple[int, ...]


def _rebuild_tensor(storage: StorageRef, offset: int, shape: tuple[int, ...], stride: tuple[int, ...],
                    *_: Any) -> TensorRef:
    return TensorRef(storage, int(offset), tuple(int(s) for s in shape), tuple(int(s) for s in stride))


class _StorageType:
    def __init__(self, name: str) -> None:
        self.dtype, self.itemsize = _STORAGES[name]


class _Unpickler(pickle.Unpickler):
    """Only plain containers and torch's tensor references: anything else is refused."""

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("collections", "OrderedDict"):
            from collections import OrderedDict

            return OrderedDict
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return _rebuild_tensor
        if module == "torch" and name in _STORAGES:
            return _StorageType(name)
        raise pickle.UnpicklingError(f"{module}.{name} is not allowed in a model file")

    def persistent_load(self, pid: Any) -> StorageRef:
        if not (isinstance(pid, tuple) and len(pid) >= 3 and pid[0] == "storage"
                and isinstance(pid[1], _StorageType)):
            raise pickle.UnpicklingError(f"unexpected storage reference {pid!r}")
        return StorageRef(str(pid[2]), pid[1].dtype, pid[1].itemsize)


def read(path: Path) -> tuple[dict[str, Any], zipfile.ZipFile, str]:
    """The saved dict (tensors as TensorRef), the open archive and its folder prefix; ModelFileError otherwise."""
    if not path.is_file():
        raise ModelFileError(f"no model file at {path}")
    try:
        archive = zipfile.ZipFile(path)
        pickles = [n for n in archive.namelist() if n.endswith("/data.pkl")]
        if len(pickles) != 1:
            raise ModelFileError(f"{path} is not a saved model (no data.pkl in it)")
        prefix = pickles[0][: -len("data.pkl")]
        if archive.read(prefix + "byteorder").strip() not in (b"little", b""):
            raise ModelFileError(f"{path} was saved on a big-endian machine; re-save it on a little-endian one")
        with archive.open(pickles[0]) as fh:
            state = _Unpickler(fh).load()
    except ModelFileError:
        raise
    except (OSError, zipfile.BadZipFile, KeyError, pickle.UnpicklingError, EOFError, ValueError, TypeError) as exc:
        first = (str(exc).splitlines() or [""])[0][:200]
        raise ModelFileError(f"{path} is not a saved model ({type(exc).__name__}: {first})") from None
    if not isinstance(state, dict) or not {"config", *NETWORKS} <= set(state):
        raise ModelFileError(f"{path} is not a model saved by a fedrl worker (no actor/critic/config in it)")
    return state, archive, prefix


def _tensor_bytes(archive: zipfile.ZipFile, prefix: str, ref: TensorRef) -> bytes:
    numel = 1
    for n in ref.shape:
        numel *= n
    expected: list[int] = []
    step = 1
    for n in reversed(ref.shape):
        expected.insert(0, step)
        step *= n
    if numel > 1 and tuple(s for s, n in zip(ref.stride, ref.shape, strict=True) if n > 1) != tuple(
            s for s, n in zip(expected, ref.shape, strict=True) if n > 1):
        raise ModelFileError("a network tensor of the model is not contiguous")
    data = archive.read(f"{prefix}data/{ref.storage.key}")
    start = ref.offset * ref.storage.itemsize
    return data[start: start + numel * ref.storage.itemsize]


def network_digest(path: Path) -> str:
    """sha256 (hex) of the model's actor and critic tensors: each one's network, name, dtype, shape and bytes."""
    state, archive, prefix = read(path)
    h = hashlib.sha256()
    with archive:
        for net in NETWORKS:
            tensors = state[net]
            if not isinstance(tensors, dict):
                raise ModelFileError(f"{path}: its {net} is not a state dict")
            for name in sorted(tensors):
                ref = tensors[name]
                if not isinstance(ref, TensorRef):
                    raise ModelFileError(f"{path}: {net} {name} is not a tensor")
                try:
                    raw = _tensor_bytes(archive, prefix, ref)
                except KeyError:
                    raise ModelFileError(f"{path}: the data of {net} {name} is missing") from None
                h.update(f"{net}.{name}:{ref.storage.dtype}:{list(ref.shape)}\n".encode())
                h.update(raw)
    return h.hexdigest()


def provenance(path: Path) -> dict[str, Any] | None:
    """The provenance a worker recorded in the model (None for a model saved before models carried one)."""
    state, archive, _ = read(path)
    archive.close()
    value = state.get("provenance")
    return value if isinstance(value, dict) else None


def solvers(summary: RunSummary) -> list[str]:
    """The ids of a run's workers that solved their task, in the order they solved it (episodes, then id)."""
    return [w.id for w in sorted(summary.workers, key=lambda w: (w.episodes, w.id)) if w.solved]


def resolve(path: Path) -> Path:
    """The model file ``path`` names: itself, or for a run folder the model of its first worker to solve."""
    if not path.is_dir():
        if not path.exists():
            raise ModelFileError(f"no model file or run folder at {path}")
        return path
    try:
        solved = solvers(RunSummary.read(path))
    except (OSError, ValueError) as exc:
        raise ModelFileError(f"{path} is a folder but not a finished run folder (its summary.json: "
                             f"{type(exc).__name__}: {exc})") from None
    if not solved:
        raise ModelFileError(f"no worker of the run in {path} solved its task, so it has no model to start from")
    first = solved[0]
    model = mature_model(path / "models", first)
    if not model.is_file():
        raise ModelFileError(f"{path}: its first worker to solve is {first}, but {model} does not exist (was the "
                             "run started without a model folder?)")
    return model


@dataclass(frozen=True)
class InitModel:
    """A warm start's model: the path as given, the file it resolves to, and its network digest."""

    given: str
    file: Path
    digest: str

    @classmethod
    def open(cls, path: Path | str) -> InitModel:
        """Resolve and digest ``path`` (a model file or a run folder); ModelFileError with the reason otherwise."""
        file = resolve(Path(path))
        return cls(str(path), file, network_digest(file))


def checked(path: Path) -> Path:
    """``path`` as given, once it names a model (a ModelFileError, one line at settings time, when it does not)."""
    resolve(path)
    return path


#: A settings field naming a model file or a run folder (``--init-model``), checked when the settings load.
ModelPath = Annotated[Path, AfterValidator(checked)]
