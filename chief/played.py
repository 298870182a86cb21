"""What each worker played, counted or not, from the run's records (summary.json, chief/audit.py).

Every submission carries its worker's ``played`` counts (protocol.messages.Played): the episodes and env steps of
its life in the run so far. The records keep them on counted episodes and on refused submissions that tell more
(runtime.records.RefusedRecord). A worker played the sum, over its lives, of the largest counts on record; the chief
counted its counted episodes' records; the rest was refused (stale, out of window...) or never arrived.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

from protocol.messages import Played
from runtime.records import AnyRecord, EpisodeRecord, PlayedTotals, RefusedRecord


@dataclass
class PlayedTally:
    """The largest ``played`` counts on record, by worker and life, and each worker's counted episodes and steps."""

    lives: dict[str, dict[str, tuple[int, int]]] = field(default_factory=dict)
    counted: dict[str, tuple[int, int]] = field(default_factory=dict)

    def advances(self, worker: str, played: Played) -> bool:
        """Whether ``played`` tells more of what ``worker`` played than the tally holds."""
        episodes, steps = self.lives.get(worker, {}).get(played.life, (0, 0))
        return played.episodes > episodes or played.steps > steps

    def add(self, record: AnyRecord) -> None:
        """Take one record of metrics.jsonl (the ones that carry no counts change nothing)."""
        if isinstance(record, EpisodeRecord):
            self.count(record.worker, record.steps, record.played)
        elif isinstance(record, RefusedRecord) and record.played is not None:
            self.play(record.worker, record.played)

    def count(self, worker: str, steps: int, played: Played | None) -> None:
        """A counted episode of ``steps`` env steps, and what its worker said it played."""
        episodes, total = self.counted.get(worker, (0, 0))
        self.counted[worker] = (episodes + 1, total + steps)
        if played is not None:
            self.play(worker, played)

    def play(self, worker: str, played: Played) -> None:
        """What ``worker`` said it played, in the life it says."""
        lives = self.lives.setdefault(worker, {})
        episodes, steps = lives.get(played.life, (0, 0))
        lives[played.life] = (max(episodes, played.episodes), max(steps, played.steps))

    def totals(self) -> dict[str, PlayedTotals]:
        """Each worker's totals (by worker id, in order of its first ``played`` counts); {} when none were sent."""
        out = {}
        for worker, lives in self.lives.items():
            episodes, steps = (sum(counts) for counts in zip(*lives.values(), strict=True))
            counted_episodes, counted_steps = self.counted.get(worker, (0, 0))
            out[worker] = PlayedTotals(episodes=episodes, steps=steps, counted_episodes=counted_episodes,
                                       counted_steps=counted_steps, refused_episodes=episodes - counted_episodes,
                                       refused_steps=steps - counted_steps)
        return out


def played_totals(records: Iterable[AnyRecord]) -> dict[str, PlayedTotals]:
    """Each worker's played, counted and refused episodes and env steps from metrics.jsonl's records."""
    tally = PlayedTally()
    for record in records:
        tally.add(record)
    return tally.totals()
