"""The worker: a learner on its own environment, federated by the chief (paper Section III, Algorithm 2).

- ``worker.learners``: the registry of learners, each one file beside the others: ``worker.ppo`` (Actor-Critic PPO,
  the paper's: Eq. 2-7 as functions, ``PPOLearner``), ``worker.sac`` (Soft Actor-Critic), ``worker.dqn`` (Double
  DQN); what they share: ``worker.federation`` (the federation's seams), ``worker.offpolicy`` and ``worker.replay``
  (the off-policy learners' replay and schedule), ``worker.nets`` (the network pieces).
- ``worker.envs``: the supported environments, their termination conditions and learner presets, and the
  per-device action noise of Section V-B-1.
- ``worker.train_local``: one worker without federation, for experiments and preset tuning.
- ``worker.service``: the MQTT adapter that runs Algorithm 2 against the chief.
"""

from runtime.extras import require

require("learn", "torch", "gymnasium")  # the worker learns: one clear line where only .[bridge] was installed
