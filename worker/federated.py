"""Algorithm 2 (one worker of the federation) without the transport: play an episode, say what to send the chief,
apply the chief's answer. worker/service.py carries it over a connection (MQTT, or the in-memory hub with which
deploy/inprocess.py runs a whole federation in one process).

Per episode (paper Algorithm 2): act until the episode ends, storing transitions; PI = mean of the last PI_WINDOW
returns. If PI >= TC over PI_WINDOW episodes, the worker's submission is its mature actor (MatureParams). Otherwise it
runs its learner's update (worker/learners.py: K PPO steps, or SAC's gradient steps) and submits the episode's actor
gradient with its PI (WorkerUpdate), then applies the chief's answer: the aggregate gradient through its actor's
optimizer, or a mature actor blended in with its keep weight (Eq. 11). Each submission carries a receipt of what it did
with the previous round's answer.

``state()`` is everything a worker goes on from; ``restore`` takes it up in a new process (worker/resume.py). A worker
that starts at a later episode without one (new networks) says so in its first receipt (``restarted``).

Once the chief has accepted the mature actor (``accepted``), the worker has finished: it submits no mature actor
again, and goes on sharing only when the strategy lets finishers help.
Under a per-step strategy (a ``RoundShape`` of K > 1 rounds per episode, protocol/rounds.py) the learner's K mini-batch
steps are K rounds: each step's actor and critic gradients are submitted, and the chief's mean of them is what the
worker's optimizers apply.

A warm-started worker may learn gently (``warm_lr``, ``warm_factor``): at a fraction of its learner's rates, and at
its learner's own only while its last few episodes all fell short of TC.

    submission = algo.play()                 # the episode, then its first submission
    while submission is not None:
        submission = algo.apply(answer_to(submission))   # the next step's submission, or None after the last

Under a bounded staleness S (``max_staleness``, per-episode strategies only) the worker need not wait: ``owed`` are
its rounds whose answer it has not applied yet, oldest first; ``take`` applies, in round order, the answers that have
come; it plays on while ``waits`` is false (at most S rounds owed), and ``give_up`` marks the oldest owed answer
missed after a reply timeout. With S = 0 this is the loop above. Every receipt says which round's answer was applied
and the first episode played with it (``Receipt.episode``); the answers applied between two submissions all travel
in the next one, the last as ``receipt``, the others as ``earlier_receipts``.

    submission = algo.play()
    while True:
        send(submission); algo.take(answers_so_far())
        if not algo.waits: break             # else: wait for the oldest owed answer, take it, check again
"""

from __future__ import annotations

import logging
import math
import secrets
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from protocol.messages import (
    STAT_BOUNDS,
    ChiefAck,
    ChiefAggregate,
    ChiefTransfer,
    MatureParams,
    Played,
    Receipt,
    WorkerUpdate,
)
from protocol.rigtime import SECONDS_LIMIT, EpisodeTime
from protocol.rounds import PER_EPISODE, RoundShape
from protocol.tasks import PI_WINDOW, performance_index, solved
from protocol.tensors import answer_digest, check_spec, digest, pack_arrays, unpack_arrays
from worker.envs import rng_states, set_rng_states
from worker.episode import run_episode
from worker.learners import Learner
from worker.nets import StepGradients

log = logging.getLogger("worker")


#: Episodes in a row short of TC after which a warm-started learner takes its full rates (``warm_factor``).
WARM_PATIENCE = 3


def warm_factor(returns: list[float], tc: float, warm_lr: float) -> float:
    """The factor of a warm-started learner's rates after ``returns``: 1 once its last ``WARM_PATIENCE`` episodes all
    fell short of TC (the model it started from does not do this device's task: it must learn), ``warm_lr`` otherwise
    (it does; a fall is the sampled policy's, and a full-rate update after it would un-learn the model:
    docs/how-to/lab.md)."""
    recent = returns[-WARM_PATIENCE:]
    return 1.0 if len(recent) == WARM_PATIENCE and all(r < tc for r in recent) else warm_lr


class Algorithm2:
    """One worker's side of every round, from ``first_episode`` on. ``life`` names this worker's life in the run
    (protocol.messages.Played; drawn at random when not given)."""

    def __init__(self, worker_id: str, env: gym.Env, learner: Learner, tc: float, seed: int,
                 first_episode: int = 1, shape: RoundShape = PER_EPISODE, life: str | None = None,
                 max_staleness: int = 0, warm_lr: float = 1.0) -> None:
        if shape.per_episode not in (1, learner.config.update_epochs):
            raise ValueError(f"the chief runs {shape.per_episode} rounds per episode, but this worker's learner takes "
                             f"{learner.config.update_epochs} steps per episode")
        if max_staleness and shape.per_step:
            raise ValueError(f"a staleness of {max_staleness} needs one round per episode, not {shape.per_episode}")
        self.worker_id = worker_id
        self.env = env
        self.learner = learner
        self.tc = tc
        self.seed = seed
        self.first_episode = first_episode
        self.shape = shape
        self.episode = first_episode  # the episode played last (or next, before the first play)
        self.step = 0  # the mini-batch step of the open submission
        self.returns: list[float] = []
        self.total_steps = 0
        self.life = life or secrets.token_hex(8)
        self.receipt: Receipt | None = None  # what was done with the last answer applied
        self._noted: list[Receipt] = []  # the answers applied since the last submission, oldest first
        self._sent: tuple[int, list[Receipt]] = (0, [])  # the round of the last submission and the receipts it carried
        self.max_staleness = max_staleness
        self.warm_lr = warm_lr
        self.owed: list[int] = []  # rounds submitted whose answer is not applied yet, oldest first (per-episode)
        if first_episode > 1:  # a worker that starts at a later episode holds no answer before it, and says so
            self.receipt = Receipt(round=shape.number(first_episode) - 1, applied="restarted")
            self._noted.append(self.receipt)
        self.actor_spec = learner.actor_spec()
        self._played = False
        self._batch: Any = None  # the learner's prepare() of an open per-step episode
        self._own: StepGradients | None = None  # this step's own gradients (applied if no answer comes)
        self._last = (0.0, 0)  # the episode's return and env steps
        self._rig: dict[str, Any] = {}  # the episode's rig time as the wire takes it (rigs only)
        self.refused_answer: str | None = None  # why the last answer was not applied
        self._finished = False

    @property
    def pi(self) -> float | None:
        return performance_index(self.returns) if self.returns else None

    @property
    def played(self) -> Played:
        """Every episode and env step played so far, counted by the chief or not (sent with each submission)."""
        return Played(life=self.life, episodes=max(1, len(self.returns)), steps=self.total_steps)

    @property
    def finished(self) -> bool:
        """Whether the chief holds this worker's mature actor (it may go on helping)."""
        return self._finished

    @property
    def next_episode(self) -> int:
        """The episode ``play()`` plays next."""
        return self.episode + 1 if self._played else self.first_episode

    @property
    def per_step(self) -> bool:
        return self.shape.per_step

    @property
    def round(self) -> int:
        """The round of the open submission (episode and step)."""
        return self.shape.number(self.episode, self.step)

    def play(self) -> WorkerUpdate | MatureParams:
        """Play the next episode; return its first submission: the mature actor once PI >= TC, else the gradient
        of this episode's learner update (of its first mini-batch step, under a per-step strategy)."""
        if self._played:
            self.episode += 1
        self._played, self.step = True, 0
        ret, steps = run_episode(self.env, self.learner, seed=self.seed if self.episode == self.first_episode else None)
        self.returns.append(ret)
        self.total_steps += steps
        self._last = (ret, steps)
        self._rig = _rig_fields(self.env)
        if self.warm_lr != 1.0:  # before this episode's update
            self.learner.scale_learning_rates(warm_factor(self.returns, self.tc, self.warm_lr))
        if not self._finished and solved(self.returns, self.tc):
            return MatureParams(worker_id=self.worker_id, episode=self.episode, episode_return=ret, pi=self.pi,
                                recent_returns=self.returns[-PI_WINDOW:], steps=steps,
                                params=pack_arrays(self.learner.actor_parameters()), **self._receipts(),
                                played=self.played, **self._rig)
        return self._first_update()

    def accepted(self, ack: ChiefAck) -> None:
        """The chief acknowledged the mature actor of the episode just played: this worker has finished (Algorithm 2).
        A ValueError, nothing changed, for an acknowledgement of another worker or episode, or a refusal."""
        if ack.worker_id != self.worker_id or ack.episode != self.episode or not ack.accepted:
            raise ValueError(f"{self.worker_id} handed over its mature actor of episode {self.episode}, not the one "
                             f"of {ack.worker_id}'s episode {ack.episode} (accepted: {ack.accepted})")
        self._finished = True

    def refused(self, mature: MatureParams) -> WorkerUpdate:
        """The chief refused the mature actor: learn on, submitting this episode as an ordinary update."""
        return self._first_update()

    def _first_update(self) -> WorkerUpdate:
        if self.per_step:
            self._batch = self.learner.prepare()
            return self._step_update()
        stats = self.learner.update()
        if self.round not in self.owed:
            self.owed.append(self.round)
        return self._update(self.learner.actor_gradient(), None, stats)

    def _step_update(self) -> WorkerUpdate:
        """Step ``self.step``'s own mini-batch gradients, to be averaged by the chief. A non-finite step (which the
        worker would skip alone) is shared as zeros: the others' mean still moves every worker alike."""
        assert self._batch is not None
        self._own = own = self.learner.minibatch_gradients(self._batch)
        return self._update(_shared(own.actor, self.actor_spec), _shared(own.critic, self.learner.critic_spec()), own)

    def _update(self, actor: dict[str, np.ndarray], critic: dict[str, np.ndarray] | None, stats: Any) -> WorkerUpdate:
        ret, steps = self._last
        return WorkerUpdate(worker_id=self.worker_id, episode=self.episode, step=self.step, episode_return=ret,
                            pi=self.pi, recent_returns=self.returns[-PI_WINDOW:], steps=steps,
                            gradient=pack_arrays(actor), **self._receipts(), played=self.played,
                            critic_gradient=pack_arrays(critic) if critic is not None else None,
                            **_loss_fields(stats), **(self._rig if self.step == 0 else {}))

    def apply(self, reply: ChiefAggregate | ChiefTransfer | None) -> WorkerUpdate | None:
        """Apply the chief's answer to the open submission (None: no answer came) and return the next submission
        of this episode (under a per-step strategy), or None when the episode's rounds are done.

        An answer whose tensors do not fit this worker's networks is not applied: ``refused`` then says why (the
        receipt says ``missed``), and under a per-step strategy the worker takes its own step, as without answer.
        """
        more = self.step + 1 < self.shape.per_episode
        receipt = self._answer(self.round, reply, self.episode if more else self.episode + 1)
        if receipt.applied == "missed" and self.per_step and self._own is not None:
            self.learner.apply_step(self._own.critic, self._own.actor)  # no usable answer: our own step
        if more:
            self.step += 1
            return self._step_update()
        self._batch = self._own = None
        return None

    @property
    def waits(self) -> bool:
        """Whether this worker must wait for an answer before it plays on: more than ``max_staleness`` of its rounds
        are unanswered."""
        return len(self.owed) > self.max_staleness

    def take(self, answers: Mapping[int, ChiefAggregate | ChiefTransfer]) -> list[int]:
        """Apply, in round order, the answers that have come to the rounds this worker owes (``owed``), up to the
        first whose answer has not come; returns the rounds applied (an answer that does not fit is noted as
        ``missed``, with ``refused_answer`` saying why, and counts as taken)."""
        taken: list[int] = []
        while self.owed and self.owed[0] in answers:
            round_ = self.owed[0]
            self._answer(round_, answers[round_], self.episode + 1)
            taken.append(round_)
        return taken

    def give_up(self) -> int:
        """No answer to the oldest owed round came in time: note it as missed and play on; returns that round."""
        round_ = self.owed[0]
        self._answer(round_, None, self.episode + 1)
        return round_

    def _answer(self, round_: int, reply: ChiefAggregate | ChiefTransfer | None, episode: int) -> Receipt:
        """Apply round ``round_``'s answer (None: none came) and note its receipt, first used in ``episode``."""
        receipt = Receipt(round=round_, applied="missed")
        self.refused_answer = None
        try:
            if reply is not None and isinstance(reply, ChiefTransfer):
                keep = reply.keep_weights.get(self.worker_id)
                if keep is not None:
                    check_spec(reply.params, self.actor_spec, "transfer")
                    self.learner.blend_actor(unpack_arrays(reply.params), keep)  # Eq. 11
                    log.info("%s blended in %s's mature actor (keep %.3f)", self.worker_id, reply.source_worker, keep)
                receipt = Receipt(round=round_, applied="transfer", digest=digest(reply.params), keep=keep)
            elif reply is not None:
                receipt = self._apply_aggregate(reply, round_)
        except ValueError as err:
            self.refused_answer = str(err)
        if round_ in self.owed:
            self.owed.remove(round_)
        return self._note(receipt, episode)

    def _note(self, receipt: Receipt, episode: int) -> Receipt:
        """Keep an answer's receipt, first used in ``episode``, for the next submission."""
        self.receipt = receipt.model_copy(update={"episode": episode})
        self._noted.append(self.receipt)
        return self.receipt

    def _receipts(self) -> dict[str, Any]:
        """The receipts a submission carries: every answer applied since the last submission, the last as
        ``receipt`` (none when nothing was applied); a refused mature actor's episode, submitted again as an
        update, carries the same."""
        if self._sent[0] != self.round:
            self._sent, self._noted = (self.round, self._noted), []
        sent = self._sent[1]
        return {"receipt": sent[-1] if sent else None, "earlier_receipts": tuple(sent[:-1])}

    @property
    def skipped_rounds(self) -> range:
        """Under a per-step strategy whose finishers help: the rounds of the episode this worker finished in, which
        it took no step of (its MatureParams was the first); :meth:`catch_up` applies their answers."""
        return self.shape.rounds_of(self.episode)

    def catch_up(self, answers: dict[int, ChiefAggregate]) -> list[int]:
        """Apply, in order, the answers of the rounds of the finishing episode (``skipped_rounds``) that every other
        worker applied, so that this helper's networks and optimizers are again the others'. Stops at the first
        missing or unusable answer; returns the rounds applied. The receipt then names the last of them."""
        applied: list[int] = []
        last: Receipt | None = None
        for round_ in self.skipped_rounds:
            reply = answers.get(round_)
            if not isinstance(reply, ChiefAggregate):
                break
            try:
                last = self._apply_aggregate(reply, round_)
            except ValueError as err:
                self.refused_answer = str(err)
                break
            applied.append(round_)
        if last is not None:
            self._note(last, self.episode + 1)
        return applied

    def _apply_aggregate(self, reply: ChiefAggregate, round_: int) -> Receipt:
        """Apply round ``round_``'s aggregate; its receipt (a ValueError, nothing applied, when it does not fit this
        worker's networks)."""
        if not self.per_step:
            if reply.gradient is not None:
                check_spec(reply.gradient, self.actor_spec, "aggregate")
                self.learner.apply_gradient(unpack_arrays(reply.gradient))  # Algorithm 2: update pi_theta with g_bar
        else:
            if reply.gradient is None or reply.critic_gradient is None:
                raise ValueError(f"round {round_}: a per-step aggregate without its actor and critic gradients")
            check_spec(reply.gradient, self.actor_spec, "aggregate")
            check_spec(reply.critic_gradient, self.learner.critic_spec(), "aggregate critic")
            self.learner.apply_step(unpack_arrays(reply.critic_gradient),  # the same mean step as every other worker
                                    unpack_arrays(reply.gradient))
        return Receipt(round=round_, applied="aggregate", digest=answer_digest(reply.gradient, reply.critic_gradient))

    def state(self) -> dict[str, Any]:
        """Everything this worker's side of the run goes on from, as tensors and plain data (a worker's resumable
        state, worker/resume.py): the episode and step bookkeeping, the PI window, the receipts of the answers
        applied (and, under a staleness, the rounds still owed), this worker's life (its played counts go on), the
        learner (networks, optimizers, observation statistics, sampling RNG, trajectory memory), an open per-step
        episode's batch and own step, and the env's RNGs."""
        own = self._own
        return {"first_episode": self.first_episode, "episode": self.episode, "step": self.step,
                "played": self._played, "returns": list(self.returns), "total_steps": self.total_steps,
                "receipt": self.receipt.model_dump() if self.receipt is not None else None, "last": list(self._last),
                "life": self.life, "noted": [r.model_dump() for r in self._noted], "owed": list(self.owed),
                "sent": [self._sent[0], [r.model_dump() for r in self._sent[1]]],
                "rig": dict(self._rig), "finished": self._finished, "learner": self.learner.state_dict(),
                "memory": self.learner.memory_state(), "env_rngs": rng_states(self.env),
                "batch": None if self._batch is None else vars(self._batch).copy(),
                "own": None if own is None else {**vars(own), "critic": _torch(own.critic), "actor": _torch(own.actor)}}

    def restore(self, state: dict[str, Any]) -> None:
        """Go on from ``state()`` output taken from a worker of the same task and networks (a ValueError, raised by
        the learner or the env, when they do not fit)."""
        self.learner.load_state_dict(state["learner"])
        self.learner.load_memory(state["memory"])
        set_rng_states(self.env, state["env_rngs"])
        self.first_episode, self.episode, self.step = state["first_episode"], state["episode"], state["step"]
        self._played, self.returns, self.total_steps = state["played"], list(state["returns"]), state["total_steps"]
        self.receipt = None if state["receipt"] is None else Receipt.model_validate(state["receipt"])
        self.life, self.owed = state["life"], list(state["owed"])
        self._noted = [Receipt.model_validate(r) for r in state["noted"]]
        self._sent = (state["sent"][0], [Receipt.model_validate(r) for r in state["sent"][1]])
        self._last, self._rig, self._finished = (state["last"][0], state["last"][1]), state["rig"], state["finished"]
        self._batch = None if state["batch"] is None else self.learner.BATCH(**state["batch"])
        own = state["own"]
        self._own = None if own is None else self.learner.STEP(**{**own, "critic": _numpy(own["critic"]),
                                                                  "actor": _numpy(own["actor"])})

    def close(self) -> None:
        close: Any = getattr(self.env, "close", None)
        if close is not None:
            close()


def _rig_fields(env: Any) -> dict[str, Any]:
    """The rig time of the episode just played (protocol/rigtime.py), as WorkerUpdate/MatureParams fields; empty for
    an env that is no rig (the gymnasium tasks)."""
    timing: EpisodeTime | None = getattr(env, "episode_time", None)
    if not isinstance(timing, EpisodeTime):
        return {}
    return {"balance_steps": timing.balance_steps, "balance_s": _seconds(timing.balance_s),
            "reset_s": _seconds(timing.reset_s)}


def _seconds(value: float) -> float:
    """Seconds as the wire bounds them (finite, 0..SECONDS_LIMIT), to the microsecond."""
    return round(min(max(0.0, value), SECONDS_LIMIT), 6) if math.isfinite(value) else 0.0


def _shared(grads: dict[str, np.ndarray] | None, spec: dict[str, tuple[int, ...]]) -> dict[str, np.ndarray]:
    """A network's step gradients as sent: float32 arrays, zeros where the step had none."""
    return {k: grads[k].astype(np.float32) if grads else np.zeros(shape, np.float32) for k, shape in spec.items()}


def _torch(arrays: dict[str, np.ndarray] | None) -> dict[str, torch.Tensor] | None:
    return None if arrays is None else {k: torch.from_numpy(np.array(v)) for k, v in arrays.items()}


def _numpy(tensors: dict[str, torch.Tensor] | None) -> dict[str, np.ndarray] | None:
    return None if tensors is None else {k: v.numpy().copy() for k, v in tensors.items()}


def _loss_fields(stats: Any) -> dict[str, float | None]:
    """The statistics of the learner's update (or step) as the wire takes them: None where absent, not finite or
    outside the wire's bounds (protocol.messages.STAT_BOUNDS). approx_kl is >= 0 in exact arithmetic; float32
    rounding can leave it at about -1e-8, which is sent as 0."""
    out: dict[str, float | None] = {}
    for key, (low, high) in STAT_BOUNDS.items():
        value = getattr(stats, key, None)
        if value is not None and key == "approx_kl" and -1e-6 < value < 0:
            value = 0.0
        out[key] = float(value) if value is not None and math.isfinite(value) and low <= value <= high else None
    return out
