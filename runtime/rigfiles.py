"""Per-rig files: a file given for every rig, or a folder with one file per rig, rig i of a run taking the folder's
i-th ``*.json`` file in name order (the rig whose seed is S takes file ``worker_index(S)``: deploy.run_local gives rig
i and worker i the seed ``worker_seed(base, i)``, protocol/tasks.py). Rig profiles (services/qube_sim/profile.py) and
the bridge's identified model (``--rig-model``) are chosen this way."""

from __future__ import annotations

from pathlib import Path

from protocol.tasks import worker_index


class RigFileError(ValueError):
    """No file for a rig: one line saying why."""


def folder_files(folder: Path, what: str = "rig profile") -> list[Path]:
    """The per-rig files of a folder, in the order rigs take them (RigFileError for a folder without any)."""
    files = sorted(folder.glob("*.json"))
    if not files:
        raise RigFileError(f"{what} folder {folder}: no *.json file in it")
    return files


def rig_file(source: Path, seed: int | None, what: str = "rig profile") -> Path:
    """``source`` itself, or for a folder the file of the rig of seed ``seed`` (None: its first file)."""
    if not source.is_dir():
        return source
    files = folder_files(source, what)
    index = 0 if seed is None else worker_index(seed)
    if index >= len(files):
        raise RigFileError(f"{what} folder {source}: rig {index} (seed {seed}) has no file; the folder holds "
                           f"{len(files)} (rigs 0-{len(files) - 1}, its *.json files in name order)")
    return files[index]
