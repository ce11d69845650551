"""Options for the whole suite: ``--hardware DEVICE`` runs the device contract suites (tests/nodes/drivers)
on a real device as well as on the simulated one; ``--long`` also runs the tests marked ``long`` (minutes
each, e.g. SIGINT at 40 moments), which the README's test command and CI leave out. Registered here so that
they work from the repository root."""

import contextlib
import fcntl

import pytest
from hypothesis import settings

# No time limit on a hypothesis example: the suite checks results, not speed (that is ``polarstripe bench``);
# hypothesis's default 200 ms deadline failed a 0.3-ms pattern test that took 415 ms once on a loaded machine
settings.register_profile("polarstripe", deadline=None)
settings.load_profile("polarstripe")


def pytest_addoption(parser):
    parser.addoption("--long", action="store_true", help="also run the tests marked long (minutes each)")
    group = parser.getgroup("hardware", "device contract suites on real hardware")
    group.addoption(
        "--hardware",
        action="append",
        default=[],
        metavar="DEVICE",
        help="also run the device contract suites on this real device: a CAN channel (can0) for the CiA 402 "
        "suite, a serial port (/dev/ttyUSB0) for the ELLx suite; repeatable",
    )
    group.addoption("--hardware-node-id", type=int, default=5, help="CANopen node id of the real drive")
    group.addoption("--hardware-eds", default=None, help="EDS of the real drive (default: the shipped one)")
    group.addoption("--hardware-address", default="0", help="ELLx address of the real device")


# The files that take longest (tens of seconds to minutes: whole launches, the murk's renders), longest first
# (measured in a full run at c7f0ab8, load 4-9: the CPU of each file's tests and of the processes they start;
# the whole suite's was ~1140 s). They run first, so that the workers share out the short files at the end and
# finish together. pyproject.toml's ``--no-loadscope-reorder`` keeps this order: by default xdist (>= 3.6)
# sorts the work by its number of tests, which sent these files of a few tests each to the end, where one
# worker ran them alone.
LONGEST_FIRST = (
    "tests/launch/test_sim_launch.py",          # ~155 s CPU: six launches, three of them the full demo
    "tests/launch/test_soak.py",                # ~90 s: the warm-up and 36 s of scanning
    "tests/tools/test_calibrate.py",            # ~65 s, most in one fixture: 8 poses rendered at sigma_t = 2
    "tests/launch/test_sigint.py",              # ~80 s: six launches
    "tests/nodes/test_foxglove_bridge.py",      # ~70 s: the demo recorded, its export, import and replay
    "tests/planning/test_sweep.py",             # ~45 s
    "tests/imaging/test_port_calibration.py",   # ~40 s
    "tests/tools/test_replay.py",               # ~40 s
    "tests/planning/test_medium_fit.py",
    "tests/launch/test_liveness_launch.py",
    "tests/runtime/test_launch.py",
    "tests/sim/test_mitsuba_port.py",
    "tests/nodes/test_planner_node.py",
    "tests/tools/test_render_cli.py",
    "tests/sim/test_port.py",
    "tests/launch/",
    "tests/sim/test_all_orders.py",
    "tests/sim/test_transport.py",
    "tests/sim/test_multiple.py",
    "tests/planning/test_planner.py",
    "tests/nodes/test_run_state.py",
    "tests/planning/test_plan_plot.py",
    "tests/planning/test_validate.py",
    "tests/sim/test_render_orders_cli.py",
    "tests/planning/test_plan_cli.py",          # ~11 s; every other file took under 11 s
)

# The files whose tests run the whole sim rig (seven or more node processes scanning, each with its own
# heartbeat deadline of 1 s; a chaos soak, two demos at once): one unit of xdist's work, so that one worker
# runs them one after another while the others run the rest. Two of them at once on a 2-core machine (the
# soak beside the two demos, CI at 18 min) starved nodes past their deadlines: a compositor silent for 9 s, a
# demo ending with exit 1. The smaller launches (a half rig, dry runs, a respawned node) stay files of their
# own: all of them in the unit made it the suite's longest path (7.5 of 10.7 min). (Not ``--dist loadgroup``:
# with pytest 9.2 it silently ignores its groups, pytest-xdist#1386.)
LAUNCHES = (
    "tests/launch/test_sim_launch.py",
    "tests/launch/test_soak.py",
    "tests/launch/test_sigint.py",
    "tests/nodes/test_foxglove_bridge.py",
    "tests/tools/test_replay.py",
)


@pytest.hookimpl(optionalhook=True)  # xdist's hook: pytest knows it only with xdist loaded
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` (pyproject.toml), except that the files of :data:`LAUNCHES` are one unit."""
    if config.getvalue("dist") != "loadfile":
        return None  # another --dist on the command line: xdist's own
    from xdist.scheduler import LoadScopeScheduling

    class LaunchesTogether(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            return "launches" if path.startswith(LAUNCHES) else path

    return LaunchesTogether(config, log)


def _cost_rank(item) -> int:
    path = item.nodeid.split("::")[0]
    return next((k for k, prefix in enumerate(LONGEST_FIRST) if path.startswith(prefix)), len(LONGEST_FIRST))


def pytest_collection_modifyitems(config, items):
    items.sort(key=_cost_rank)  # stable: each file's tests keep their order
    if config.getoption("--long"):
        return
    skip = pytest.mark.skip(reason="a long test (minutes): run with --long")
    for item in items:
        if "long" in item.keywords:
            item.add_marker(skip)


GIGE_LOCK = "/tmp/polarstripe-gige-fake.lock"


@contextlib.contextmanager
def gige_port():
    """Hold the GigE Vision control port 127.0.0.1:3956 of this host (a simulator binds it): test runs on the
    same host take turns instead of failing."""
    with open(GIGE_LOCK, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


@pytest.fixture
def gige_lock():
    """The GigE Vision port held for a test that starts its own simulator (``polarstripe camera fake``)."""
    with gige_port():
        yield


@pytest.fixture(scope="module")
def gige_fake():
    """Aravis's GigE Vision simulator on 127.0.0.1 for a test module (nodes/drivers/aravis_system.py); its
    ``lost_ratio`` is put back to 0 by :func:`gige`. Without Aravis this fails: the tests run in CI."""
    from polarstripe.nodes.drivers.aravis_system import FakeGvCamera

    with gige_port(), FakeGvCamera("127.0.0.1") as fake:
        yield fake


@pytest.fixture
def gige(gige_fake):
    """The module's simulator, sending every packet at the start and end of each test."""
    gige_fake.lost_ratio = 0.0
    yield gige_fake
    gige_fake.lost_ratio = 0.0
