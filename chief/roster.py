"""Who takes part in a run: the chief admits workers by their hello (pure code, no MQTT).

A worker is admitted when it runs the run's env and learner (protocol/learners.py) and its actor and critic have the
same tensor names and shapes, and its learner the same number K of mini-batch steps per episode, as the first admitted
worker's (Eq. 9 and Eq. 11 need aligned parameters; a per-step strategy needs the same K everywhere), and it started
from the run's model: the network digest of its ``--init-model`` (runtime/model_file.py), or none from scratch. The
run's model is the chief's own ``--init-model`` when it has one (``init_model_known``), else the first admitted
worker's. Once the run has started, only its workers may say hello again (a restarted worker, which then learns the open
round from the re-announced RunStart).
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class Roster:
    env_id: str
    algo: str = "ppo"  # the run's learner
    started: bool = False
    actor_spec: dict[str, tuple[int, ...]] | None = None
    critic_spec: dict[str, tuple[int, ...]] | None = None
    update_steps: int = 0
    hosts: dict[str, str] = field(default_factory=dict)
    init_model: str | None = None  # the digest of the model every worker starts from (None: from scratch)
    init_model_known: bool = False  # whether init_model is decided (by the chief's setting or the first worker)
    init_model_path: str = ""  # that model's path as given (the chief's, or the first worker's)

    @property
    def workers(self) -> list[str]:
        return sorted(self.hosts)

    def offer(self, worker_id: str, env_id: str, actor_spec: dict[str, tuple[int, ...]],
              host: str = "", critic_spec: dict[str, tuple[int, ...]] | None = None,
              update_steps: int = 0, init_model: str | None = None,
              init_model_path: str = "", algo: str = "ppo") -> tuple[str, str] | None:
        """Admit (or re-admit) a worker; returns (reason, detail) when it is turned away."""
        if self.started and worker_id not in self.hosts:
            return "late_worker", "the run has started without this worker"
        if env_id != self.env_id:
            return "wrong_env", f"worker runs {env_id!r}, this run is {self.env_id!r}"
        if algo != self.algo:
            return "wrong_algo", f"worker runs learner {algo!r}, this run {self.algo!r}"
        if self.init_model_known and init_model != self.init_model:
            return "wrong_init_model", (f"worker started from {_model(init_model)}, this run from "
                                        f"{_model(self.init_model)}")
        spec = {k: tuple(v) for k, v in actor_spec.items()}
        critic = {k: tuple(v) for k, v in (critic_spec or {}).items()}
        if self.actor_spec is None:
            self.actor_spec, self.critic_spec, self.update_steps = spec, critic, update_steps
        elif spec != self.actor_spec:
            return "wrong_model", "actor shape differs from the other workers'"
        elif critic != self.critic_spec or update_steps != self.update_steps:
            return "wrong_model", "critic shape or learner steps per episode differ from the other workers'"
        if not self.init_model_known:
            self.init_model, self.init_model_path, self.init_model_known = init_model, init_model_path, True
        self.hosts[worker_id] = host
        return None


def _model(digest: str | None) -> str:
    return f"model {digest[:12]}" if digest else "scratch"
