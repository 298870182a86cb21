"""Edges that fail over and rejoin (docs/explanation/tiered.md, "When an edge dies"): pure code, time passed in.

Each edge's workers are a **group**, named after the edge they were started behind (RunStart ``edges``). A group's
rounds go through its own edge while that edge lives; when the root finds the edge dead, they go through a
**stand-in**: another live edge of the same site (RunStart ``stand_ins``). The stand-in sums the group in a partial
of its own, exactly as the dead edge would have (the same workers, the same Eq. 9 sum and clipping, keyed by the
group at the root), so the run's aggregates, records and audit are those of the run without the death.

**When an edge is dead.** An edge says ``online`` every ``HEARTBEAT`` seconds (EdgeStatus; a partial counts too).
It is dead when its last will came (``offline``: the broker lost its connection) and it said nothing for
``WILL_GRACE`` seconds since (a broker restart delivers every client's will, and an edge that merely reconnected
says ``online`` again at once), or when it said nothing for ``silence_limit`` seconds (a third of the round timeout,
at most ``SILENCE_LIMIT``: a hung edge, or a host gone without a TCP reset). Only an edge the root heard, or named in
its RunStart, can be found dead. So a dead edge's workers move within ``WILL_GRACE`` of its will, and at most
``silence_limit(round_timeout)`` after its last word: within one round timeout.

**Where its workers go**: the live edge of the same site serving the fewest workers (ties by name); when no live edge
of its site is left, the root itself (``ROOT_EDGE``: an edge chief in the root's process, chief/edge.py RootStandIn,
whose workers read the root's own topics). A group never moves back: a restarted edge rejoins at the root's open
round (RunStart ``round``) and serves the groups the RunStart gives it, its own when it came back before it was found
dead, else none until another edge dies.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field

from protocol.topics import ROOT_EDGE

#: Seconds between an edge's ``online`` statuses.
HEARTBEAT = 1.0
#: What the root logs when it finds an edge dead (a launcher that restarts edges waits for it: chief.service,
#: deploy.run_local); ``dead_edge_in`` reads it back.
DEAD = "edge {} is dead"


_DEAD_LINE = re.compile(re.escape(DEAD).replace(re.escape("{}"), r"(\S+)"))


def dead_edge_in(line: str) -> str | None:
    """The edge a root's log line says it found dead (``DEAD``), else None."""
    found = _DEAD_LINE.search(line)
    return found.group(1) if found else None


#: Seconds an edge whose last will came may take to say ``online`` again before it is dead.
WILL_GRACE = 2.0
#: The most seconds of silence before an edge is dead (``silence_limit``).
SILENCE_LIMIT = 10.0


def silence_limit(round_timeout: float) -> float:
    """Seconds of silence after which an edge is dead: a third of the round timeout, at most SILENCE_LIMIT, at least
    three heartbeats."""
    return max(3 * HEARTBEAT, min(SILENCE_LIMIT, round_timeout / 3))


def dead(last_heard: float, will_at: float | None, now: float, round_timeout: float) -> bool:
    """Whether an edge last heard at ``last_heard`` (its will at ``will_at``, None if none came since) is dead."""
    if will_at is not None and will_at >= last_heard and now - will_at >= WILL_GRACE:
        return True
    return now - last_heard >= silence_limit(round_timeout)


def serving(group: str, stand_ins: Mapping[str, str]) -> str:
    """The edge a group's rounds go through now."""
    return stand_ins.get(group, group)


def groups_of(edge: str, edges: Mapping[str, str], stand_ins: Mapping[str, str]) -> dict[str, list[str]]:
    """The groups ``edge`` serves, each with its workers (``edges``: worker -> its group)."""
    out: dict[str, list[str]] = {}
    for w, group in sorted(edges.items()):
        if serving(group, stand_ins) == edge:
            out.setdefault(group, []).append(w)
    return out


def stand_in(group_site: str | None, sites: Mapping[str, str | None], alive: set[str],
             load: Mapping[str, int]) -> str:
    """The live edge of ``group_site`` serving the fewest workers (``load``), ties by name; the root itself
    (ROOT_EDGE) when none is left."""
    candidates = sorted((load.get(e, 0), e) for e in alive if sites.get(e) == group_site and e != ROOT_EDGE)
    return candidates[0][1] if candidates else ROOT_EDGE


@dataclass
class EdgeWatch:
    """What a root knows of its edges' lives: when each was last heard, whose will came, which are dead."""

    heard: dict[str, float] = field(default_factory=dict)
    wills: dict[str, float] = field(default_factory=dict)
    sites: dict[str, str | None] = field(default_factory=dict)
    started: dict[str, bool] = field(default_factory=dict)
    found_dead: set[str] = field(default_factory=set)

    def expect(self, edges: set[str], now: float) -> None:
        """Edges the run names, as if heard now (one that never speaks is found dead after ``silence_limit``)."""
        for e in edges:
            self.heard.setdefault(e, now)

    def status(self, edge: str, online: bool, now: float, started: bool = True, site: str | None = None
               ) -> bool:
        """An edge's status (``online``, or its will); True when it comes back: dead before, or it lost the run
        (it says it holds no RunStart after it held one: it restarted)."""
        if not online:
            self.wills[edge] = now
            return False
        back = edge in self.found_dead or (self.started.get(edge, False) and not started)
        self.heard[edge], self.sites[edge], self.started[edge] = now, site, started
        self.wills.pop(edge, None)
        self.found_dead.discard(edge)
        return back

    def alive_now(self, edge: str, now: float) -> None:
        """Something else came from the edge (a partial): it lives."""
        if edge in self.heard and edge not in self.found_dead:
            self.heard[edge] = now

    def newly_dead(self, now: float, round_timeout: float) -> list[str]:
        """The edges found dead now (each once, until it comes back)."""
        out = sorted(e for e, t in self.heard.items()
                     if e not in self.found_dead and dead(t, self.wills.get(e), now, round_timeout))
        self.found_dead.update(out)
        return out

    def alive(self) -> set[str]:
        return set(self.heard) - self.found_dead


def fail_over(dead_edges: list[str], edges: Mapping[str, str], stand_ins: Mapping[str, str], watch: EdgeWatch
              ) -> dict[str, str]:
    """The new stand-ins once ``dead_edges`` died: each group served by a dead edge goes to a live edge of its site
    (``stand_in``; the group's site is its own edge's), or to the root when none is left."""
    out = dict(stand_ins)
    alive = watch.alive()
    for group in sorted(set(edges.values())):
        if serving(group, out) not in dead_edges:
            continue
        load = {e: sum(len(ws) for ws in groups_of(e, edges, out).values()) for e in alive}
        chosen = stand_in(watch.sites.get(group), watch.sites, alive, load)
        if chosen == group:
            out.pop(group, None)
        else:
            out[group] = chosen
    return out


def served_by_root(stand_ins: Mapping[str, str]) -> list[str]:
    """The groups the root itself serves (ROOT_EDGE)."""
    return sorted(g for g, e in stand_ins.items() if e == ROOT_EDGE)
