"""The network pieces every learner shares: the kind of action space, the MLP and its configuration fields, the
seeded initialisation, the one conversion from the API's arrays to torch, Eq. 11's blend, and the shapes of what a
gradient step and an update report (``StepGradients``, ``UpdateStats``: the statistics every learner has; each learner
declares its own beside them, and the wire, the records and TensorBoard take whichever of the wire's statistics a
learner's carry).
"""

from __future__ import annotations

import contextlib
import itertools
import math
import threading
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from torch import nn

ACTIVATIONS: dict[str, type[nn.Module]] = {"tanh": nn.Tanh, "relu": nn.ReLU, "leaky_relu": nn.LeakyReLU}
#: Held while a learner seeds its networks from torch's process-wide RNG, so that learners built in several threads at
#: once (deploy/inprocess.py) each draw from their own seed.
_GLOBAL_RNG = threading.Lock()


class FromDict:
    """A learner configuration (a dataclass): built from ``asdict(config)`` (unknown keys are an error), and checked
    with ``_validate`` after its init."""

    hidden_sizes: tuple[int, ...]
    activation: str
    obs_scale: tuple[float, ...] | None
    max_grad_norm: float | None

    def _validate(self, positive: tuple[str, ...] = (), at_least_one: tuple[str, ...] = (), unit: tuple[str, ...] = (),
                  problems: tuple[tuple[bool, str], ...] = ()) -> None:
        """Normalise the network fields (hidden sizes as ints, the input scale as floats) and raise one ValueError
        naming every problem: actor_lr, reward_scale and the ``positive`` fields must be finite and > 0, batch_size,
        update_epochs and ``at_least_one`` >= 1, gamma and ``unit`` in [0, 1], max_grad_norm > 0 or None;
        ``problems``: the learner's own (is it wrong, what to say)."""
        self.hidden_sizes = tuple(int(h) for h in self.hidden_sizes)
        self.obs_scale = None if self.obs_scale is None else tuple(float(x) for x in self.obs_scale)
        found = [message for wrong, message in (
            (self.obs_scale is not None and not all(0 < x < float("inf") for x in self.obs_scale),
             "obs_scale entries must be finite and > 0"),
            (not self.hidden_sizes or min(self.hidden_sizes) < 1, "hidden_sizes must be non-empty positive integers"),
            (self.activation not in ACTIVATIONS, f"activation must be one of {sorted(ACTIVATIONS)}")) if wrong]
        found += [f"{n} must be finite and > 0" for n in ("actor_lr", "reward_scale", *positive)
                  if not (getattr(self, n) > 0 and math.isfinite(getattr(self, n)))]
        found += [f"{n} must be >= 1" for n in ("batch_size", "update_epochs", *at_least_one) if getattr(self, n) < 1]
        found += [f"{n} must be in [0, 1]" for n in ("gamma", *unit) if not 0.0 <= getattr(self, n) <= 1.0]
        if self.max_grad_norm is not None and not self.max_grad_norm > 0:
            found.append("max_grad_norm must be > 0 or None")
        found += [message for wrong, message in problems if wrong]
        if found:
            raise ValueError(f"invalid {type(self).__name__}: " + "; ".join(found))

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> Any:
        unknown = set(values) - {f.name for f in fields(cls)}  # type: ignore[arg-type]
        if unknown:
            raise ValueError(f"unknown {cls.__name__} keys: {sorted(unknown)}")
        return cls(**dict(values))


def action_kind(action_space: spaces.Space) -> tuple[bool, tuple[int, ...], int]:
    """(discrete, action shape, units of one action head) of a Discrete or Box action space."""
    if isinstance(action_space, spaces.Discrete):
        return True, (), int(action_space.n)
    if isinstance(action_space, spaces.Box):
        return False, tuple(action_space.shape), int(np.prod(action_space.shape))
    raise ValueError(f"unsupported action space {action_space!r}: use Discrete or Box")


def mlp(
    in_dim: int, hidden: tuple[int, ...], out_dim: int, activation: str, ortho: bool, out_gain: float
) -> nn.Sequential:
    """Linear-activation stack; orthogonal init (CleanRL style) when ``ortho``."""
    layers: list[nn.Module] = []
    sizes = (in_dim, *hidden)
    for a, b in itertools.pairwise(sizes):
        layers += [_linear(a, b, ortho, math.sqrt(2.0)), ACTIVATIONS[activation]()]
    layers.append(_linear(sizes[-1], out_dim, ortho, out_gain))
    return nn.Sequential(*layers)


def _linear(in_dim: int, out_dim: int, ortho: bool, gain: float) -> nn.Linear:
    layer = nn.Linear(in_dim, out_dim)
    if ortho:
        nn.init.orthogonal_(layer.weight, gain)
        nn.init.zeros_(layer.bias)
    return layer


@contextlib.contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Networks built inside draw their initial weights from ``seed``, without disturbing torch's global RNG."""
    with _GLOBAL_RNG, torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


def tensors(arrays: Mapping[str, np.ndarray], net: nn.Module) -> dict[str, torch.Tensor]:
    """The learners' one conversion from their API's arrays to torch: float32 copies of those of ``arrays`` named like
    a parameter of ``net``. The names and shapes were checked where the arrays came in (the worker checks the chief's
    answers against its networks, protocol.tensors.check_spec; the codec that they are finite)."""
    return {name: torch.from_numpy(np.array(arrays[name], dtype=np.float32))
            for name, _ in net.named_parameters() if name in arrays}


@torch.no_grad()
def blend(net: nn.Module, params: Mapping[str, Any], keep_weight: float) -> None:
    """Eq. 11 in place on ``net``: theta = w_T * theta + (1 - w_T) * theta_bar, with w_T = ``keep_weight`` in [0, 1].
    A ValueError for a weight outside [0, 1], before anything changed."""
    w = float(keep_weight)
    if not (math.isfinite(w) and 0.0 <= w <= 1.0):
        raise ValueError(f"transfer: keep_weight must be in [0, 1], got {keep_weight!r}")
    theta_bar = tensors(params, net)
    for name, p in net.named_parameters():
        p.mul_(w).add_(theta_bar[name], alpha=1.0 - w)


@dataclass
class StepGradients:
    """One mini-batch step's gradients (float32 arrays; None where not finite) and the statistics every learner has;
    a learner with more subclasses it (worker/ppo.py) and names its class in ``STEP``."""

    critic: dict[str, np.ndarray] | None
    actor: dict[str, np.ndarray] | None
    actor_loss: float
    critic_loss: float
    entropy: float


@dataclass
class UpdateStats:
    """Means over the gradient steps of one ``update()``: the statistics every learner has (its own losses; NaN where
    a learner has none, which is not sent). A learner with more subclasses it."""

    actor_loss: float
    critic_loss: float
    entropy: float
    memory_size: int
    skipped_steps: int = 0  # critic/actor steps skipped because the loss or gradient was not finite
