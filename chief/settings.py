"""Settings of the chief, and of a federation as the launchers describe it (torch-free: launchers import it)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from chief import strategies
from runtime.model_file import ModelPath
from runtime.settings import OneOf, RunKeySettings, RunMqttSettings, Settings, TaskName, setting

PolicyName = Annotated[str, OneOf(strategies.names)]


class FederationSettings(Settings):
    """What a run is: the task, the federation strategy, the seed and the limits of its rounds."""

    env: TaskName = setting("CartPole-v0", "task every worker learns")
    policy: PolicyName = setting(strategies.DEFAULT, "federation strategy (python -m chief.strategies describes them)")
    seed: int = setting(1, "base seed; worker i uses seed*1000 + i")
    max_episodes: int = setting(2000, "M, the most rounds a run may take", ge=1)
    round_timeout: float = setting(30.0, "seconds a round waits for a silent worker after the first submission",
                                   gt=0)


class ChiefSettings(RunMqttSettings, RunKeySettings, FederationSettings):
    """The chief of a federated RL run (paper Algorithm 1)."""

    workers: int = setting(4, "number of workers to wait for", ge=1)
    start_timeout: float = setting(300.0, "seconds to wait for all workers before starting with those present",
                                   gt=0)
    idle_timeout: float = setting(120.0, "end the run when every unfinished worker is offline this long", gt=0)
    run_dir: Path = setting(Path("runs/latest"), "folder for summary.json, metrics.jsonl, learning_curve.png and "
                            "the chief's saved state")
    init_model: ModelPath | None = setting(
        None, "the model every worker must start from (its --init-model: a model file or a run folder); unset: the "
        "first worker's, or scratch", metavar="PATH")

