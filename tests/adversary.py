"""``python -m tests.adversary``: a worker that lies (for the Byzantine tests). It learns like any other worker but
submits its gradient sign-flipped and scaled by FEDRL_LIE_SCALE (default -5): within the chief's norm bounds, and
pulling a linear mean the wrong way. Everything else it sends is honest."""

from __future__ import annotations

import os
import sys
from typing import Any

from protocol.messages import WorkerUpdate
from protocol.tensors import pack_arrays, unpack_arrays
from worker import federated
from worker.__main__ import main

SCALE = float(os.environ.get("FEDRL_LIE_SCALE", "-5"))
_honest_update = federated.Algorithm2._update


def _lying_update(self: federated.Algorithm2, *args: Any, **kwargs: Any) -> WorkerUpdate:
    """The honest update with its gradients poisoned (whatever the honest ``_update`` takes)."""
    msg = _honest_update(self, *args, **kwargs)
    update = {"gradient": _poison(msg.gradient)}
    if msg.critic_gradient is not None:
        update["critic_gradient"] = _poison(msg.critic_gradient)
    return msg.model_copy(update=update)


def _poison(packed: Any) -> Any:
    return pack_arrays({k: (SCALE * v).astype(v.dtype) for k, v in unpack_arrays(packed).items()})


federated.Algorithm2._update = _lying_update  # type: ignore[method-assign]

if __name__ == "__main__":
    sys.exit(main())
