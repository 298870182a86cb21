"""Settings of the chief, and of a federation as the launchers describe it (torch-free: launchers import it)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import field_validator, model_validator

from chief import strategies, tiers
from protocol import learners
from protocol.rounds import STALENESS_LIMIT
from protocol.topics import check_edge, check_id
from runtime.model_file import ModelPath
from runtime.settings import (
    LearnerName,
    LearnerTaskSettings,
    OneOf,
    QubeActions,
    RunKeySettings,
    RunMqttSettings,
    TaskName,
    qube_actions_setting,
    setting,
)

PolicyName = Annotated[str, OneOf(strategies.names)]


class FederationSettings(LearnerTaskSettings):
    """What a run is: the task, the federation strategy, the seed and the limits of its rounds."""

    env: TaskName = setting("CartPole-v0", "task every worker learns")
    qube_actions: QubeActions = qube_actions_setting()
    algo: LearnerName = setting(learners.DEFAULT, "learner every worker runs (python -m worker.learners lists them)")
    policy: PolicyName = setting(strategies.DEFAULT, "federation strategy (python -m chief.strategies describes them)")
    seed: int = setting(1, "base seed; worker i uses seed*1000 + i")
    max_episodes: int = setting(2000, "M, the most rounds a run may take", ge=1)
    round_timeout: float = setting(30.0, "seconds a round waits for a silent worker after the first submission",
                                   gt=0)
    max_staleness: int = setting(0, "S, bounded staleness: a worker plays its next episode while up to S of its own "
                                 "rounds are unanswered (0: it waits for every answer; per-episode strategies only)",
                                 ge=0, le=STALENESS_LIMIT)

    quorum: int = setting(0, "k of a k-of-n round: it closes when k of the workers it waits for submitted; a later "
                          "submission for it is dropped (refused as late, its worker applies the round's answer); 0: "
                          "every worker. Per-episode strategies; with edges, k is counted across them "
                          "(docs/explanation/tiered.md)", ge=0)

    @property
    def strategy(self) -> strategies.Strategy:
        """The run's strategy (chief/strategies), resolved from ``policy`` (which the settings checked)."""
        return strategies.get(self.policy)

    def tiering(self) -> tuple[int, str | None]:
        """The edge chiefs the run gets (``edges`` of a tiered launcher, else 0) and, when its strategy cannot be
        split across edges, 0 with the note that says it runs flat."""
        edges = getattr(self, "edges", 0)
        if edges and not tiers.decomposable(self.strategy):
            return 0, tiers.why_flat(self.strategy)
        return edges, None

    @model_validator(mode="after")
    def _quorum_fits(self) -> FederationSettings:
        if self.quorum and not self.strategy.allows_staleness:
            raise ValueError(f"--quorum {self.quorum}: policy {self.policy!r} shares every PPO step, whose mean each "
                             "worker must apply with its own; use 0")
        return self

    @model_validator(mode="after")
    def _staleness_fits(self) -> FederationSettings:
        if self.max_staleness and not self.strategy.allows_staleness:
            raise ValueError(f"--max-staleness {self.max_staleness}: policy {self.policy!r} shares every PPO step, "
                             "whose answer each worker must apply before its next step; use 0")
        return self


def quorum_problem(quorum: int, workers: int | None) -> str | None:
    """Why a k-of-n round cannot be (None: it can, or the workers are not known yet): k > n never closes. With edges
    k is counted across them (each closes its part with its share, chief/tiers.py ``edge_quorum``)."""
    if quorum and workers is not None and quorum > workers:
        return (f"--quorum {quorum}: a round cannot wait for more than its {workers} workers; use 1..{workers}, or 0 "
                "for all of them")
    return None


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
    role: Literal["chief", "edge"] = setting("chief", "chief: the run's chief (the root when --edges > 0); edge: an "
                                             "edge chief, closing its workers' part of each round for the root "
                                             "(docs/explanation/tiered.md)")
    edge_id: str | None = setting(None, "--role edge: this edge's id (its workers say it in their --edge)")
    edges: int = setting(0, "--role chief: how many edge chiefs feed this root (0: a flat run, every worker's update "
                         "to this chief)", ge=0, le=1024)
    site: str | None = setting(None, "--role edge: the site this edge runs at (unset: the run's one broker); a dead "
                               "edge's workers move to a live edge of its site (chief/failover.py)")

    @field_validator("edge_id")
    @classmethod
    def _edge_id(cls, value: str | None) -> str | None:
        return None if value is None else check_edge(value)

    @field_validator("site")
    @classmethod
    def _site(cls, value: str | None) -> str | None:
        return None if value is None else check_id(value, "site name")

    @model_validator(mode="after")
    def _role_fits(self) -> ChiefSettings:
        if (self.role == "edge") != (self.edge_id is not None):
            raise ValueError("--edge-id goes with --role edge, and --role edge needs one")
        if self.role == "edge" and self.edges:
            raise ValueError("--edges is the root chief's setting, not an edge's")
        if self.edges and not tiers.decomposable(self.strategy):
            raise ValueError(f"--edges {self.edges}: {tiers.why_flat(self.strategy)}")
        problem = quorum_problem(self.quorum, self.workers if self.role == "chief" else None)
        if problem is not None:
            raise ValueError(problem)
        return self

