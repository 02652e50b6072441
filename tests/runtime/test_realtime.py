"""Real-time options in real child processes: granted when privileged, refused cleanly when not."""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import sys
import textwrap

import pytest

from usmswitch.runtime.realtime import apply_realtime

CHILD = textwrap.dedent(
    """
    import json, os, threading
    from usmswitch.runtime.realtime import apply_realtime, drop_realtime
    cpu = min(os.sched_getaffinity(0))
    result = apply_realtime(sched_fifo_priority=50, cpu_affinity=[cpu], mlockall=True)
    helper = {}
    def run():
        helper["dropped"] = drop_realtime()
        helper["policy"] = os.sched_getscheduler(0)
    t = threading.Thread(target=run)
    t.start()
    t.join()
    locked_kib = 0
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmLck:"):
                locked_kib = int(line.split()[1])
    print(json.dumps({
        "applied": result.applied, "refused": result.refused, "cpu": cpu,
        "policy": os.sched_getscheduler(0), "affinity": sorted(os.sched_getaffinity(0)),
        "helper": helper, "locked_kib": locked_kib,
    }))
    """
)


def run_child(prefix: list[str], preexec=None) -> dict:
    proc = subprocess.run(
        [*prefix, sys.executable, "-c", CHILD],
        capture_output=True,
        text=True,
        timeout=60,
        preexec_fn=preexec,
    )
    assert proc.returncode == 0, proc.stderr  # a refusal never stops the process
    return json.loads(proc.stdout.strip().splitlines()[-1])


def unprivileged_limits() -> None:
    """In the child: no real-time priority and a small locked-memory limit (lowering is always allowed)."""
    resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
    resource.setrlimit(resource.RLIMIT_MEMLOCK, (64 * 1024, 64 * 1024))


def test_refusals_are_reported_and_the_process_carries_on():
    prefix = []
    if os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            pytest.skip(
                "running as root without setpriv: cannot drop CAP_SYS_NICE/CAP_IPC_LOCK for the child"
            )
        # Root would be granted everything: take the two capabilities out of the child's reach.
        prefix = ["setpriv", "--bounding-set=-sys_nice,-ipc_lock", "--inh-caps=-sys_nice,-ipc_lock", "--"]
    out = run_child(prefix, unprivileged_limits)
    assert set(out["refused"]) == {"sched_fifo_priority", "mlockall"}, out
    assert out["refused"]["sched_fifo_priority"].startswith("EPERM")
    assert "RLIMIT_RTPRIO 0" in out["refused"]["sched_fifo_priority"]
    assert "RLIMIT_MEMLOCK is 65536 bytes and no CAP_IPC_LOCK" in out["refused"]["mlockall"]
    # What could be applied was: the affinity needs no privilege.
    assert out["applied"] == {"cpu_affinity": str(out["cpu"])}
    assert out["affinity"] == [out["cpu"]]
    assert out["policy"] == os.SCHED_OTHER and out["locked_kib"] == 0


def test_granted_when_privileged():
    out = run_child([])
    if "sched_fifo_priority" in out["refused"]:
        pytest.skip(f"this process may not use SCHED_FIFO: {out['refused']['sched_fifo_priority']}")
    assert out["applied"]["sched_fifo_priority"] == "SCHED_FIFO 50"
    assert out["policy"] == os.SCHED_FIFO
    # A helper thread started by the loop thread inherits FIFO and drops it.
    assert out["helper"] == {"dropped": True, "policy": os.SCHED_OTHER}
    if "mlockall" in out["applied"]:
        assert out["locked_kib"] > 0
    else:
        assert "RLIMIT_MEMLOCK" in out["refused"]["mlockall"]


def test_a_cpu_that_does_not_exist_is_refused_in_process():
    before = os.sched_getaffinity(0)
    result = apply_realtime(cpu_affinity=[4095])
    assert not result.ok and result.refused["cpu_affinity"].startswith("EINVAL")
    assert "cpus [4095]" in result.refused["cpu_affinity"]
    assert os.sched_getaffinity(0) == before
    assert apply_realtime().applied == {} and apply_realtime().ok


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"sched_fifo_priority": 100}, "got 100"),
        ({"sched_fifo_priority": -1}, "got -1"),
        ({"sched_fifo_priority": True}, "got True"),
        ({"cpu_affinity": [-1]}, "got -1"),
        ({"cpu_affinity": ["2"]}, "got '2'"),
    ],
)
def test_bad_arguments_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        apply_realtime(**kwargs)
