"""The liveness watch (runtime/liveness.py): deadlines, exits and incarnations of peers on a given clock;
``wait_for(…, peers=…)`` through the node harness (virtual clock); the run state a respawned node restores."""

import json

import pytest
from polarstripe.msgs import Heartbeat, Log
from polarstripe.runtime.bus import BusTimeout
from polarstripe.runtime.liveness import STARTING_DEADLINE_S, Liveness, PeerLost, RunState, incarnation
from polarstripe.runtime.node import Node, NodeError
from polarstripe.runtime.testing import NodeHarness


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def beat(node, *, inc=0, pid=100, period_ms=250, **extra):
    return Heartbeat(node=node, pid=pid, uptime_s=1.0,
                     counters={"incarnation": inc, "heartbeat_ms": period_ms, **extra})


def test_a_peer_is_lost_after_four_of_its_own_periods_without_a_beat():
    clock = Clock()
    live = Liveness(clock)
    live.heard(beat("emitter", period_ms=250))
    live.heard(beat("grabber", period_ms=1000))
    clock.t = 0.99
    assert live.check(["emitter", "grabber"]) is None
    clock.t = 1.01
    lost = live.check(["grabber", "emitter"])
    assert isinstance(lost, PeerLost) and lost.node == "emitter" and not lost.respawned
    assert "node 'emitter' lost: no heartbeat for 1.01 s (deadline 1 s)" == str(lost)
    assert live.check(["grabber"]) is None  # 4 x 1 s for the slower one
    clock.t = 4.2
    assert live.check(["grabber"]).node == "grabber"


def test_a_peer_in_its_setup_has_the_longer_starting_deadline_and_then_the_short_one():
    clock = Clock()
    live = Liveness(clock)
    live.heard(beat("planner", starting=1))
    clock.t = STARTING_DEADLINE_S - 0.1  # a setup that holds the interpreter (compiling, planning)
    assert live.check(["planner"]) is None
    live.heard(beat("planner"))  # setup done: the ordinary deadline of 4 periods from now on
    clock.t += 1.01
    assert live.check(["planner"]).node == "planner"
    live.heard(beat("emitter", starting=1))
    clock.t += STARTING_DEADLINE_S + 0.1
    assert "no heartbeat for 10.10 s" in str(live.check(["emitter"]))


def test_peers_never_heard_are_not_judged_and_a_beat_keeps_a_peer_alive():
    clock = Clock()
    live = Liveness(clock)
    clock.t = 100.0
    assert live.check(["nobody"]) is None
    live.heard(beat("emitter"))
    clock.t = 100.9
    live.heard(beat("emitter"))
    clock.t = 101.8
    assert live.check(["emitter"]) is None


def test_an_orderly_exit_is_a_loss_at_once():
    clock = Clock()
    live = Liveness(clock)
    live.heard(beat("compositor", exiting=1))
    lost = live.check(["compositor"])
    assert lost.node == "compositor" and "exited" in lost.reason


def test_a_new_incarnation_is_a_loss_of_the_old_one_and_then_back():
    clock = Clock()
    live = Liveness(clock)
    live.heard(beat("emitter", inc=0, pid=1))
    clock.t = 0.5
    live.heard(beat("emitter", inc=1, pid=2))  # died and came back between two checks
    lost = live.check(["emitter"])
    assert lost.node == "emitter" and lost.respawned and lost.incarnation == 0
    assert "respawned (incarnation 0 -> 1, pid 1 -> 2)" in lost.reason
    assert live.back("emitter", since=0) and not live.back("emitter", since=1)
    live.forgive("emitter")
    assert live.check(["emitter"]) is None
    live.heard(beat("emitter", inc=0, pid=1))  # a late beat of the old incarnation changes nothing
    assert live.peers["emitter"].pid == 2 and live.check(["emitter"]) is None


def test_a_lost_peer_stays_lost_until_a_new_incarnation_beats():
    clock = Clock()
    live = Liveness(clock)
    live.heard(beat("simulator", inc=0))
    clock.t = 2.0
    assert live.check(["simulator"]).node == "simulator"
    live.heard(beat("simulator", inc=0))  # the same incarnation, late: still a fault (its waits were cut)
    assert live.check(["simulator"]) is not None and not live.back("simulator", 0)
    live.forgive("simulator")  # not back: nothing to forgive
    assert live.check(["simulator"]) is not None
    clock.t = 5.0
    live.heard(beat("simulator", inc=1, pid=7))
    assert live.check(["simulator"]).respawned and live.back("simulator", 0)


def test_incarnation_comes_from_the_launchers_environment():
    assert incarnation({"POLARSTRIPE_INCARNATION": "3"}) == 3
    assert incarnation({}) == 0 and incarnation({"POLARSTRIPE_INCARNATION": "x"}) == 0


class Waiter(Node):
    SUBSCRIBES = {"heartbeat": Heartbeat, "chatter": Log}

    def setup(self):
        self.subscribe("chatter", mode="all")
        self.watch()


def test_wait_for_ends_when_a_peer_it_depends_on_stops_beating():
    h = NodeHarness(Waiter, name="w", namespace="/rig")
    h.queue("heartbeat", beat("emitter"))
    h.queue("heartbeat", beat("grabber", period_ms=10_000))
    with pytest.raises(PeerLost) as info:
        h.node.wait_for("chatter", timeout_s=30.0, peers=["emitter", "grabber"])
    assert info.value.node == "emitter"
    assert 1.0 < h.bus.clock <= 1.1  # the deadline plus one slice of the wait (virtual clock)
    with pytest.raises(BusTimeout):  # not a peer of this wait: only the timeout ends it
        h.node.wait_for("chatter", timeout_s=2.0, peers=["grabber"])


def test_a_wait_hands_every_arrived_beat_to_the_watch_at_once():
    """Many nodes beat faster than a wait's slices: each slice takes every beat that has arrived, so the
    watch never falls behind (a backlog would make a dead peer's last beat look recent)."""
    h = NodeHarness(Waiter, name="w", namespace="/rig")
    for i in range(50):
        h.queue("heartbeat", beat(f"n{i}"))
    h.queue("chatter", Log(level="INFO", node="x", text="hi"))
    h.node.wait_for("chatter", timeout_s=1.0, peers=["n0"])
    h.node.check_peers(["n0"])
    assert len(h.node.liveness.peers) == 50 and h.node.take("heartbeat") == []


def test_the_watched_heartbeats_feed_the_watch_in_every_read():
    h = NodeHarness(Waiter, name="w", namespace="/rig")
    h.queue("heartbeat", beat("planner", inc=2, pid=9))
    assert h.node.take("heartbeat")[0].incarnation == 2
    assert h.node.liveness.peers["planner"].incarnation == 2
    h.deliver("heartbeat", beat("emitter"))  # through the loop
    assert "emitter" in h.node.liveness.peers


def test_wait_for_with_peers_needs_a_watch():
    class Plain(Node):
        SUBSCRIBES = {"chatter": Log}

        def setup(self):
            self.subscribe("chatter")

    h = NodeHarness(Plain, name="p")
    with pytest.raises(NodeError, match="needs watch"):
        h.node.wait_for("chatter", peers=["x"])


def test_run_state_is_kept_in_the_run_directory(tmp_path):
    s = RunState(tmp_path, "emitter")
    assert s.get("next_scan_id", 1) == 1 and "next_scan_id" not in s
    s.save(next_scan_id=4)
    s.save(other="x")
    assert json.loads((tmp_path / "state" / "emitter.json").read_text()) == {"next_scan_id": 4, "other": "x"}
    again = RunState.of({"run_dir": str(tmp_path)}, "emitter")
    assert again.get("next_scan_id") == 4
    memory = RunState.of({}, "emitter")  # no launch: in memory only
    memory.save(a=1)
    assert memory.get("a") == 1 and memory.path is None
    (tmp_path / "state" / "bad.json").write_text("{not json")
    assert RunState(tmp_path, "bad").get("x") is None


_BUSY = '''
import time
from polarstripe.runtime.node import Node


class Busy(Node):
    def setup(self):
        time.sleep(1.5)  # a slow setup (the planner plans): beats say "starting" meanwhile
        self.every(0.5, self.block)

    def block(self):
        self.counters["blocked"] = 1
        time.sleep(1.0)  # a long handler: the loop is blocked, the heartbeat thread is not
        self.counters["blocked"] = 0
        self.stop("done", exit_code=0)
'''


def test_a_busy_node_keeps_beating_and_its_last_beat_says_it_exits(tmp_path):
    """A real process: beats come from their own thread while a handler blocks the loop, carry the
    launcher's incarnation and the period, and the last one says the node is exiting."""
    import os
    import subprocess
    import sys

    from polarstripe.runtime.bus import Subscriber

    (tmp_path / "busy_mod.py").write_text(_BUSY)
    env = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
           "POLARSTRIPE_INCARNATION": "2"}
    pub = f"ipc://{tmp_path}/b.pub"
    beats = []
    with Subscriber([pub], "/heartbeat", Heartbeat, mode="all") as sub:
        proc = subprocess.Popen(
            [sys.executable, "-m", "polarstripe", "node", "busy_mod:Busy", "--param", "heartbeat_s=0.05",
             "--pub", pub, "--srv", f"ipc://{tmp_path}/b.srv"],
            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, env=env, cwd=tmp_path)
        try:
            while not (beats and beats[-1].counters.get("exiting")):
                try:
                    beats.append(sub.recv(timeout_s=20.0))
                except BusTimeout:
                    break
            assert proc.wait(timeout=20) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert beats, "no heartbeat at all"
    blocked = [b for b in beats if b.counters.get("blocked")]
    assert len(blocked) >= 3, [b.counters for b in beats]  # ~20 beats in the blocked second
    assert all(b.incarnation == 2 and b.counters["heartbeat_ms"] == 50 for b in beats)
    assert beats[-1].counters.get("exiting") == 1
    assert not any(b.counters.get("exiting") for b in beats[:-1])
    starting = [bool(b.counters.get("starting")) for b in beats]
    # beats from before setup ends (the first ones may come before the subscription has joined), "ready" after
    assert any(starting) and not starting[-1], starting
    assert starting == sorted(starting, reverse=True), starting  # never "starting" again once ready


def test_a_node_may_beat_slower_than_heartbeat_s_and_its_beats_say_so():
    class Slow(Node):
        def setup(self):
            self.beat_period_s = 1.0

    h = NodeHarness(Slow, name="s", params={"heartbeat_s": 0.25})
    assert h.node.heartbeat().counters["heartbeat_ms"] == 1000
    assert NodeHarness(Waiter, name="w").node.heartbeat().counters["heartbeat_ms"] == 250
    clock = Clock()
    live = Liveness(clock)
    live.heard(h.node.heartbeat())
    clock.t = 3.9
    assert live.check(["s"]) is None  # 4 of its own periods
    clock.t = 4.1
    assert live.check(["s"]).node == "s"
