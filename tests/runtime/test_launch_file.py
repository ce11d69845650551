"""Reading launch files (runtime/launch_file.py): args and their substitution, typed keys, node classes and
params checked before anything starts; every mistake is one line naming the file, the key and the value."""

import pytest
from polarstripe.nodes.demo import Listener, Talker
from polarstripe.runtime.launch_file import LaunchError, find_launch_file, load_launch, sock_dir

_TWO = """
[launch]
namespace = "/demo"
shutdown_timeout = 2
[launch.env]
A = 1
[args]
rate = 10
count = 0
tag = "x"
listen = true
[[node]]
name = "talker"
module = "polarstripe.nodes.demo:Talker"
params = { rate_hz = "${rate}", text = "say ${tag} at ${rate}" }
respawn = "${listen}"
[[node]]
name = "listener"
module = "polarstripe.nodes.demo:Listener"
params = { count = "${count}" }
enabled = "${listen}"
required = true
"""


def _file(tmp_path, text=_TWO, name="two.toml"):
    f = tmp_path / name
    f.write_text(text)
    return f


def test_args_keep_their_type_alone_and_become_text_inside_a_string(tmp_path):
    spec = load_launch(_file(tmp_path))
    assert (spec.name, spec.namespace, spec.transport, spec.shutdown_timeout) == ("two", "/demo", "ipc", 2.0)
    assert spec.env == {"A": "1"} and spec.args == {"rate": 10, "count": 0, "tag": "x", "listen": True}
    talker, listener = spec.nodes
    assert talker.node_class is Talker and listener.node_class is Listener
    assert talker.params == {"rate_hz": 10.0, "text": "say x at 10"}  # typed by the node's Params
    assert talker.respawn is True and listener.required is True and listener.params == {"count": 0}


def test_command_line_overrides_are_strings_typed_by_the_node_and_can_leave_a_node_out(tmp_path):
    spec = load_launch(_file(tmp_path), {"rate": "25", "listen": "false"})
    assert [n.name for n in spec.nodes] == ["talker"] and spec.nodes[0].params["rate_hz"] == 25.0
    assert spec.nodes[0].respawn is False
    with pytest.raises(LaunchError, match="two.toml: unknown arg 'speed' on the command line"):
        load_launch(_file(tmp_path), {"speed": "1"})


def test_a_bad_param_value_is_rejected_with_the_node_and_param(tmp_path):
    with pytest.raises(LaunchError, match="two.toml: node 'talker': param 'rate_hz': bad value 'fast'"):
        load_launch(_file(tmp_path), {"rate": "fast"})
    with pytest.raises(LaunchError, match="rate_hz must be > 0"):
        load_launch(_file(tmp_path), {"rate": "0"})


def test_a_missing_module_or_class_names_the_node(tmp_path):
    f = _file(tmp_path, '[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Nope"\n', "m.toml")
    with pytest.raises(LaunchError, match=r"m.toml: node\[0\] \('a'\): .*has no class 'Nope'"):
        load_launch(f)


def test_shipped_launch_files_are_found_by_name_and_a_missing_file_is_one_line(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sim").mkdir()  # a directory of that name (the repository root has the sim package)
    shipped = find_launch_file("sim")
    assert shipped.name == "sim.toml" and shipped.is_file()
    assert find_launch_file("launch/sim.toml") == shipped and find_launch_file("sim.toml") == shipped
    assert find_launch_file(tmp_path / "nope.toml") == tmp_path / "nope.toml"
    with pytest.raises(LaunchError, match="nope.toml does not exist"):
        load_launch(tmp_path / "nope.toml")


@pytest.mark.parametrize(
    ("toml", "error"),
    [
        (
            '[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Talker"\ncolour="red"',
            "node[0] ('a'): unknown key 'colour'",
        ),
        (
            '[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Talker"\nrespawn="often"',
            "respawn: expected bool",
        ),
        (
            '[[node]]\nname="a"\nmodule="polarstripe.nodes.nonesuch:X"',
            "module 'polarstripe.nodes.nonesuch' not found",
        ),
        ('[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Nope"', "has no class 'Nope'"),
        (
            '[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Talker"\nparams={rate_hz="fast"}',
            "param 'rate_hz'",
        ),
        (
            '[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Talker"\nparams={speed=1}',
            "unknown param 'speed'",
        ),
        (
            '[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Talker"\nparams={rate_hz="${r}"}',
            "unknown arg ${r}",
        ),
        ('[launch]\nnamespace=3\n[[node]]\nname="a"\nmodule="m"', "namespace: expected str, got int"),
        (
            '[launch]\ntransport="udp"\n[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Talker"',
            "'ipc' or 'tcp'",
        ),
        ('[[node]]\nname="a"\n', "missing key 'module'"),
        ("[[nodes]]\nname='a'", "unknown top-level key 'nodes'"),
        ("[args]\nx=1", "needs at least one [[node]]"),
        (
            '[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Talker"\n[[node]]\nname="a"\n'
            'module="polarstripe.nodes.demo:Talker"',
            "duplicate node name 'a'",
        ),
        ("[[node]\n", "not valid TOML"),
        ('[args]\nrun_id="x"\n[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Talker"',
         "run_id is given by the launcher"),
        ('[launch]\nexclusive=["nope"]\n[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Talker"',
         "launch.exclusive names 'nope', not an arg"),
        ('[launch]\nprepare=["nocolon"]\n[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Talker"',
         "must be MODULE:FUNCTION"),
        ('[[node]]\nname="a"\nmodule="polarstripe.nodes.demo:Talker"\nrespawn_max_delay=-1',
         "must be >= 0"),
    ],
)
def test_bad_launch_files_are_rejected_with_one_clear_line(tmp_path, toml, error):
    f = tmp_path / "bad.toml"
    f.write_text(toml)
    with pytest.raises(LaunchError) as info:
        load_launch(f)
    assert error in str(info.value) and "\n" not in str(info.value)




_PER_RUN = """
[launch]
name = "pr"
exclusive = ["seg"]
[args]
seg = "ipc://${run_sock}/seg"
fixed = "bus0"
[[node]]
name = "talker"
module = "polarstripe.nodes.demo:Talker"
params = { text = "${seg} ${run_id} ${run_dir}" }
"""


def test_built_in_args_name_things_per_run_and_explicit_names_are_claimed(tmp_path):
    run = tmp_path / "runs" / "pr-1"
    spec = load_launch(_file(tmp_path, _PER_RUN), run_dir=run)
    assert spec.args["seg"] == f"ipc://{sock_dir(run)}/seg"  # <run>/sock, or a short folder for a long path
    assert spec.nodes[0].params["text"] == f"ipc://{sock_dir(run)}/seg pr-1 {run}"
    assert spec.run_dir == run and spec.exclusive == {}  # per run: nothing to claim
    spec = load_launch(_file(tmp_path, _PER_RUN), {"seg": "bus7"}, run_dir=run)
    assert spec.exclusive == {"seg": "bus7"}
    # two runs of one file never name the same thing
    a = load_launch(_file(tmp_path, _PER_RUN), run_dir=tmp_path / "runs" / "pr-1")
    b = load_launch(_file(tmp_path, _PER_RUN), run_dir=tmp_path / "runs" / "pr-2")
    assert a.args["seg"] != b.args["seg"]


def test_the_sim_launch_checks_its_args_through_the_nodes_params(tmp_path):
    too_big = r"node 'simulator'.*resolution 100000x100000 is .* beyond the limit"
    with pytest.raises(LaunchError, match=too_big):
        load_launch("sim", {"resolution": "100000x100000"})
    with pytest.raises(LaunchError, match="node 'simulator'.*resolution 4000x6000"):
        load_launch("sim", {"resolution": "4000x6000"})
    spec = load_launch("sim", run_dir=tmp_path / "sim-1")
    sim = next(n for n in spec.nodes if n.name == "simulator")
    assert sim.params["can_channel"] == f"ipc://{sock_dir(tmp_path / 'sim-1')}/can"
