"""The worker: Actor-Critic PPO on its own environment (paper Section III, Algorithm 2).

- ``worker.ppo``: the learner as pure code (networks, Eq. 2-7 as functions, ``PPOLearner``).
- ``worker.envs``: the supported environments, their termination conditions and PPO presets, and the
  per-device action noise of Section V-B-1.
- ``worker.train_local``: one worker without federation, for experiments and preset tuning.
- ``worker.service``: the MQTT adapter that runs Algorithm 2 against the chief.
"""

from runtime.extras import require

require("learn", "torch", "gymnasium")  # the worker learns: one clear line where only .[bridge] was installed
