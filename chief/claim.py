"""One chief per run: a chief holds its run with a retained, session-stamped ChiefClaim on ``fedrl/<run>/claim``.

A starting chief subscribes to the claim topic, publishes its claim (retained), and waits for its own claim to come
back: the broker delivers a retained claim left by another chief before it, and a chief running the run answers any
younger claim by publishing its own again. Of two claims the older (``since``, then the smaller session) wins
(``beats``); a chief whose claim is beaten does not start (chief.service.EXIT_CLAIMED). A chief resumed from its saved
state claims with the same session and ``since``, so it takes its run back. The claim is cleared (an empty retained
message) when the run ends. With a run key, claims carry a tag like every chief message, and an untagged or forged
claim is refused and counted. This is no broker-side lock: a broker that keeps no retained messages (the in-process
hub) cannot tell a second chief, and a chief that died for good leaves its claim until it is cleared by hand
(``mosquitto_pub -r -n -t fedrl/<run>/claim``).
"""

from __future__ import annotations

import logging
import queue
import time

from protocol import topics
from protocol.auth import admitted, signed
from protocol.codec import RejectCounter, encode
from protocol.messages import ChiefClaim
from protocol.routes import qos_of
from protocol.transport import Transport

log = logging.getLogger("chief")

#: The chief's exit code when another chief holds its run: it did not start (or stopped).
EXIT_CLAIMED = 6
#: Seconds to wait for the broker to hand back this chief's own claim (then it goes on, warning).
ECHO_TIMEOUT = 5.0
#: Seconds, beyond twice the round trip of the echo, to wait for a running chief to re-assert an older claim.
GRACE = 0.25


def beats(a: ChiefClaim, b: ChiefClaim) -> bool:
    """Whether claim ``a`` wins over claim ``b`` of another session: the older, then the smaller session."""
    return (a.since, a.session) < (b.since, b.session)


class RunClaim:
    """This chief's claim of its run over ``conn``: ``take`` at the start, ``watch`` while running, ``clear`` at
    the end."""

    def __init__(self, conn: Transport, claim: ChiefClaim, key: bytes | None, rejects: RejectCounter) -> None:
        self.conn, self.key, self.rejects = conn, key, rejects
        self.claim = signed(claim, key)
        self.topic = topics.claim(claim.run_id)
        self._seen: queue.Queue[ChiefClaim] = queue.Queue()

    def _on_message(self, topic: str, payload: bytes) -> None:
        if not payload:  # a claim cleared
            return
        msg = admitted(payload, ChiefClaim, topic=topic, key=self.key, rejects=self.rejects)
        if isinstance(msg, ChiefClaim):
            self._seen.put(msg)

    def _publish(self) -> None:
        self.conn.publish(self.topic, encode(self.claim), qos=qos_of(self.topic), retain=True)

    def take(self) -> ChiefClaim | None:
        """Claim the run; the other chief's claim that beats this one (this chief must not start), or None."""
        self.conn.subscribe(self.topic, self._on_message, qos=qos_of(self.topic))
        sent = time.monotonic()
        self._publish()
        winner: ChiefClaim | None = None
        echoed: float | None = None
        deadline = sent + ECHO_TIMEOUT
        while time.monotonic() < deadline:
            try:
                seen = self._seen.get(timeout=0.05)
            except queue.Empty:
                continue
            if seen.session == self.claim.session:
                if echoed is None:
                    echoed = time.monotonic()
                    deadline = echoed + GRACE + 2 * (echoed - sent)
            elif beats(seen, self.claim) and (winner is None or beats(seen, winner)):
                winner = seen
        if echoed is None:
            log.warning("the broker did not hand back this chief's claim of run %s within %.0f s: a second chief "
                        "for this run would go unnoticed (may this chief read %s?)", self.claim.run_id,
                        ECHO_TIMEOUT, self.topic)
        if winner is None:
            self._publish()  # ours again: a younger claim seen meanwhile may have overwritten it
        return winner

    def watch(self) -> ChiefClaim | None:
        """While running: answer a younger claim with ours again; the claim that beats ours, if one came."""
        winner = None
        while True:
            try:
                seen = self._seen.get_nowait()
            except queue.Empty:
                return winner
            if seen.session == self.claim.session:
                continue
            if beats(seen, self.claim):
                winner = seen
            else:
                log.warning("another chief (session %s on %s, pid %d) claims run %s: it is refused",
                            seen.session, seen.host or "?", seen.pid, self.claim.run_id)
                self._publish()

    def clear(self) -> None:
        """The run is over: remove the claim."""
        self.conn.unsubscribe(self.topic)
        try:
            self.conn.publish(self.topic, b"", qos=qos_of(self.topic), retain=True).wait_for_publish(timeout=5)
        except (RuntimeError, ValueError) as err:  # paho: not connected
            log.warning("could not clear the claim of run %s (%s): clear it by hand (mosquitto_pub -r -n -t %s)",
                        self.claim.run_id, err, self.topic)
