"""Algorithm 2 (one worker of the federation) without the transport: play an episode, say what to send the chief,
apply the chief's answer. worker/service.py carries it over MQTT; deploy/inprocess.py calls it directly for sweeps,
so both run the same worker logic.

Per episode (paper Algorithm 2): act until the episode ends, storing transitions; PI = mean of the last PI_WINDOW
returns. If PI >= TC over PI_WINDOW episodes, the worker's submission is its mature actor (MatureParams). Otherwise it
runs K PPO updates and submits the episode's actor gradient with its PI (WorkerUpdate), then applies the chief's
answer: the aggregate gradient through its actor's optimizer, or a mature actor blended in with its keep weight
(Eq. 11). Each submission carries a receipt of what it did with the previous round's answer.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import gymnasium as gym

from protocol.messages import ChiefAggregate, ChiefTransfer, MatureParams, Receipt, WorkerUpdate
from protocol.tasks import PI_WINDOW, performance_index, solved
from protocol.tensors import check_spec, digest, pack_arrays, unpack_arrays
from worker.episode import run_episode
from worker.ppo import PPOLearner

log = logging.getLogger("worker")


class Algorithm2:
    """One worker's side of every round, from ``first_episode`` on."""

    def __init__(self, worker_id: str, env: gym.Env, learner: PPOLearner, tc: float, seed: int,
                 first_episode: int = 1) -> None:
        self.worker_id = worker_id
        self.env = env
        self.learner = learner
        self.tc = tc
        self.seed = seed
        self.first_episode = first_episode
        self.episode = first_episode  # the episode to play next
        self.returns: list[float] = []
        self.total_steps = 0
        self.receipt: Receipt | None = None  # what was done with the last round's answer
        self.actor_spec = learner.actor_spec()

    @property
    def pi(self) -> float | None:
        return performance_index(self.returns) if self.returns else None

    def play(self) -> WorkerUpdate | MatureParams:
        """Play the next episode; return what to submit for it: the mature actor once PI >= TC, else the gradient
        of this episode's K PPO updates."""
        ret, steps = run_episode(self.env, self.learner, seed=self.seed if self.episode == self.first_episode else None)
        self.returns.append(ret)
        self.total_steps += steps
        if solved(self.returns, self.tc):
            return MatureParams(worker_id=self.worker_id, episode=self.episode, episode_return=ret, pi=self.pi,
                                recent_returns=self.returns[-PI_WINDOW:], steps=steps,
                                params=pack_arrays(self.learner.actor_parameters()), receipt=self.receipt)
        return self._update(ret, steps)

    def refused(self, mature: MatureParams) -> WorkerUpdate:
        """The chief refused the mature actor: learn on, submitting this episode as an ordinary update."""
        return self._update(mature.episode_return, mature.steps)

    def _update(self, ret: float, steps: int) -> WorkerUpdate:
        stats = self.learner.update()
        return WorkerUpdate(worker_id=self.worker_id, episode=self.episode, episode_return=ret, pi=self.pi,
                            recent_returns=self.returns[-PI_WINDOW:], steps=steps,
                            gradient=pack_arrays(self.learner.actor_gradient()), receipt=self.receipt,
                            **_loss_fields(stats))

    def apply(self, reply: ChiefAggregate | ChiefTransfer | None) -> Receipt:
        """Apply the chief's answer to the episode just submitted (None: no answer came) and move to the next
        episode. Raises ValueError for an answer whose tensors do not fit this worker's actor (nothing applied)."""
        episode = self.episode
        self.episode += 1
        self.receipt = Receipt(round=episode, applied="missed")
        if reply is None:
            return self.receipt
        if isinstance(reply, ChiefTransfer):
            keep = reply.keep_weights.get(self.worker_id)
            if keep is not None:
                check_spec(reply.params, self.actor_spec, "transfer")
                self.learner.blend_actor(unpack_arrays(reply.params), keep)  # Eq. 11
                log.info("%s blended in %s's mature actor (keep %.3f)", self.worker_id, reply.source_worker, keep)
            self.receipt = Receipt(round=episode, applied="transfer", digest=digest(reply.params), keep=keep)
            return self.receipt
        if reply.gradient is not None:
            check_spec(reply.gradient, self.actor_spec, "aggregate")
            self.learner.apply_gradient(unpack_arrays(reply.gradient))  # Algorithm 2: update pi_theta with g_bar
        self.receipt = Receipt(round=episode, applied="aggregate",
                               digest=digest(reply.gradient) if reply.gradient is not None else "")
        return self.receipt

    def close(self) -> None:
        close: Any = getattr(self.env, "close", None)
        if close is not None:
            close()


def _loss_fields(stats: Any) -> dict[str, float | None]:
    """Finite loss numbers from the learner's update stats (None where absent or not finite)."""
    out: dict[str, float | None] = {}
    for key in ("actor_loss", "critic_loss", "entropy"):
        value = getattr(stats, key, None)
        out[key] = float(value) if value is not None and math.isfinite(value) else None
    return out
