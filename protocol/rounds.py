"""A round's identity and number, defined once for the chief, the workers, the audit and the dashboard.

A round is one exchange of Algorithm 1-2: every worker submits, the chief answers. Rounds tile the episodes: a
``RoundShape`` of K rounds per episode numbers round (e, s), step s = 0..K-1 of episode e = 1, 2, ..., as

    round = (e - 1) * K + s + 1

With one round per episode (the paper's strategies) the round is the episode; a per-step strategy (``sync``) has K,
one per PPO mini-batch step. Which shape a run has is its strategy's choice (chief/strategies/); RunStart tells the
workers (``rounds_per_episode``), and every answer of the chief carries its round number.

>>> shape = RoundShape(per_episode=3)
>>> shape.number(2, 1), shape.of(5), list(shape.rounds_of(2))
(5, RoundId(episode=2, step=1), [4, 5, 6])
"""

from __future__ import annotations

from typing import Final, NamedTuple

from pydantic import BaseModel, ConfigDict, Field

#: The most rounds an episode may have (PPO's mini-batch steps per episode, K).
MAX_PER_EPISODE: Final = 1000
#: The largest bounded staleness a run may allow (RunStart.max_staleness): how many of its own rounds a worker may
#: leave unanswered while it plays on. The chief keeps submissions up to chief.rounds.AHEAD_WINDOW episodes ahead of
#: its open round, more than this.
STALENESS_LIMIT: Final = 5


class RoundId(NamedTuple):
    """A round by its place: step ``step`` (0-based) of episode ``episode`` (1-based)."""

    episode: int
    step: int = 0


class RoundShape(BaseModel):
    """How rounds tile episodes: ``per_episode`` (K) rounds each, numbered 1, 2, ... over (episode, step)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    per_episode: int = Field(default=1, ge=1, le=MAX_PER_EPISODE)

    @property
    def per_step(self) -> bool:
        """Whether a round is one mini-batch step (K > 1) rather than a whole episode."""
        return self.per_episode > 1

    def number(self, episode: int, step: int = 0) -> int:
        """The number of round (episode, step); ValueError for a step outside 0..K-1 or an episode below 1."""
        if episode < 1 or not 0 <= step < self.per_episode:
            raise ValueError(f"no round (episode {episode}, step {step}) with {self.per_episode} rounds per episode")
        return (episode - 1) * self.per_episode + step + 1

    def of(self, number: int) -> RoundId:
        """The (episode, step) of round ``number`` (>= 1)."""
        if number < 1:
            raise ValueError(f"rounds are numbered from 1, not {number}")
        episode, step = divmod(number - 1, self.per_episode)
        return RoundId(episode + 1, step)

    def episode_of(self, number: int) -> int:
        return self.of(number).episode

    def step_of(self, number: int) -> int:
        return self.of(number).step

    def rounds_of(self, episode: int) -> range:
        """The numbers of episode ``episode``'s rounds, in order."""
        first = self.number(episode)
        return range(first, first + self.per_episode)

    def last_of(self, episode: int) -> int:
        """The number of episode ``episode``'s last round."""
        return self.number(episode, self.per_episode - 1)

    def ends_episode(self, number: int) -> bool:
        """Whether round ``number`` is its episode's last."""
        return self.step_of(number) == self.per_episode - 1

    def agrees(self, number: int, episode: int, step: int = 0) -> bool:
        """Whether a message's round ``number`` is round (episode, step) of this shape."""
        return episode >= 1 and 0 <= step < self.per_episode and number == self.number(episode, step)


#: The paper's shape: one round per episode.
PER_EPISODE: Final = RoundShape()
