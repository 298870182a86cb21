"""deploy.lab's identification of rigs over MQTT (``--env qube``): every rig is asked, as a worker asks for a reset,
and its profile fitted on this host (``python -m worker.identify``).

With ``--broker`` the rigs are real bridges (or simulated ones someone started) on that broker, logged in as the
caller's FEDRL_MQTT_* say. Without it, the pipeline starts an embedded broker with its own users and ACL and one
simulated rig per worker (``python -m services.qube_sim``, rig i with seed ``worker_seed(seed, i)``, as
deploy.run_local starts them), whose physics comes from FEDRL_RIG_PROFILE in their environment, and stops them
afterwards.
"""

from __future__ import annotations

import subprocess
import sys
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING

from protocol.tasks import worker_seed
from services.broker.embedded import make_credentials, start_broker_process, stop_process

if TYPE_CHECKING:
    from deploy.lab import LabSettings

RUN_ID = "lab-identify"


def identify_over_mqtt(s: LabSettings, out: Path, todo: list[int], env: dict[str, str]) -> None:
    """Identify rigs ``todo`` into ``out/rig<i>.json``; StageFailed with the first rig that could not be."""
    from deploy.lab import StageFailed, run_child

    if not todo:
        return
    logins: dict[str, dict[str, str]] = {}
    with ExitStack() as stack:
        broker = s.broker
        if broker is None:
            workers = [f"w{i}" for i in range(s.workers)]
            creds = make_credentials(out.parent / "identify-broker", RUN_ID, workers,
                                     {f"w{i}": f"rig{i}" for i in range(s.workers)})
            log = stack.enter_context((out.parent / "identify-broker.log").open("ab"))
            proc, port = start_broker_process(credentials=creds, stdout=log, stderr=subprocess.STDOUT)
            stack.callback(stop_process, proc)
            broker = f"mqtt://127.0.0.1:{port}"
            logins = {user: {"FEDRL_MQTT_USERNAME": user, "FEDRL_MQTT_PASSWORD": password}
                      for user, password in creds.users.items()}
            for i in todo:
                rig_log = stack.enter_context((out.parent / f"identify-rig{i}.log").open("ab"))
                rig = subprocess.Popen(
                    [sys.executable, "-m", "services.qube_sim", "--rig-id", f"rig{i}", "--seed",
                     str(worker_seed(s.seed, i)), "--qube-clock", "lockstep", "--broker", broker],
                    env={**env, **logins[f"rig{i}"]}, stdout=rig_log, stderr=subprocess.STDOUT)
                stack.callback(stop_process, rig)
            print(f"[lab identify] embedded broker on {broker}; simulated rigs {', '.join(f'rig{i}' for i in todo)}")
        for i in todo:
            command = [sys.executable, "-m", "worker.identify", "--rig-id", f"rig{i}", "--broker", broker, "--out",
                       str(out / f"rig{i}.json"), "--recording-out", str(out / f"rig{i}.recording.json.gz"),
                       "--identify-attempts", str(s.identify_attempts)]
            code = run_child("identify", command, {**env, **logins.get(f"w{i}", {})})
            if code != 0:
                raise StageFailed(f"rig{i} could not be identified over MQTT (exit code {code}); see the lines above")
