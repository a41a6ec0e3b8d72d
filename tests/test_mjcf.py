"""MJCF import (`natcoord import`): the round trip through MuJoCo, the shipped imported
cases, and bad models refused with exit 2 naming the file and the element.

Round trip (measured, mujoco 4.0.0): the planar four-bar imported from cases/mjcf_four_bar.xml
and run in MuJoCo through the adapter (RK4, dt 1e-4, connect solref 1e-3 s, as the XML
asks) follows the same XML stepped directly (mj_step) to 6.5e-14 m at the loop point over
2 s; natcoord on the imported case follows the direct run to 5.2e-9 m (MuJoCo's soft
loop: its connect's error, which falls with the time constant). Bounds ~10x.
"""

from __future__ import annotations

import mujoco  # noqa: F401 - a real dependency: missing fails, never skips
import numpy as np
import pytest
from typer.testing import CliRunner

from natcoord.case.casefile import load_case
from natcoord.case.generate import write_case
from natcoord.case.mjcf import import_mjcf
from natcoord.cli import app
from natcoord.engines import adapter
from natcoord.engines.base import initial_body_states
from natcoord.outputs.result import evaluate_channels

from .conftest import CASES

pytestmark = pytest.mark.engines

SHIPPED = ("mjcf_four_bar", "mjcf_rssr")


def _direct(xml, imp, case) -> np.ndarray:
    """The loop point at the case's times, (T, d) in the case's axes: the XML stepped by
    mj_step with its own options, from the importer's (assembled) initial state."""
    m = mujoco.MjModel.from_xml_path(str(xml))
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = imp.qpos, imp.qvel
    k = int(round(case.output_dt / m.opt.timestep))
    (body, anchor), = imp.loops.values()
    out = []
    for i in range(len(case.times)):
        for _ in range(k if i else 0):
            mujoco.mj_step(m, d)
        mujoco.mj_kinematics(m, d)
        out.append(d.xpos[body] + d.xmat[body].reshape(3, 3) @ anchor)
    p = np.array(out)
    return p if imp.frame is None else p @ imp.frame[:2].T


def test_round_trip_four_bar(tmp_path):
    xml = CASES / "mjcf_four_bar.xml"
    imp = import_mjcf(xml, "rt_four_bar")
    write_case(tmp_path / "rt_four_bar.toml", imp.text)
    case = load_case(tmp_path / "rt_four_bar.toml")
    assert case.dimension == 2 and imp.frame is not None
    direct = _direct(xml, imp, case)
    (loop,) = imp.loops
    got = {}
    for engine in ("mujoco", "natcoord"):
        run = adapter(engine).run(case, initial_body_states(case), {})
        table = evaluate_channels(case, run.motion)
        got[engine] = np.column_stack([table[f"{a}_{loop}"] for a in "xy"])
    assert np.abs(direct - direct[0]).max() > 0.5  # it moves: the comparison means something
    assert np.abs(got["mujoco"] - direct).max() < 1e-12
    assert np.abs(got["natcoord"] - direct).max() < 5e-8


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_case_is_its_import(name, tmp_path):
    """The committed case's mechanism is what importing its XML writes now."""
    shipped = load_case(CASES / f"{name}.toml")
    imp = import_mjcf(CASES / f"{name}.xml", name, duration=shipped.duration)
    write_case(tmp_path / f"{name}.toml", imp.text)
    fresh = load_case(tmp_path / f"{name}.toml")
    assert [b.name for b in fresh.bodies] == [b.name for b in shipped.bodies]
    for a, b in zip(fresh.bodies, shipped.bodies, strict=True):
        assert a.mass == b.mass
        np.testing.assert_allclose(a.com, b.com, atol=1e-15)
        np.testing.assert_allclose(a.inertia, b.inertia, atol=1e-15)
    assert [(j.name, j.type, j.bodies) for j in fresh.joints] == [
        (j.name, j.type, j.bodies) for j in shipped.joints]
    assert {c.name for c in fresh.channels} <= {c.name for c in shipped.channels}


def test_rssr_is_3d_with_two_dof():
    case = load_case(CASES / "mjcf_rssr.toml")
    assert case.dimension == 3
    assert {j.type for j in case.joints} == {"revolute", "spherical"}


def test_masses_are_mujocos():
    imp = import_mjcf(CASES / "mjcf_four_bar.xml", "x")
    m = mujoco.MjModel.from_xml_path(str(CASES / "mjcf_four_bar.xml"))
    assert "mass = 2.0" in imp.text  # coupler 1.6 kg rod + 0.4 kg lump, compiled
    assert abs(m.body_mass.sum() - (0.8 + 2.0 + 1.2)) < 1e-12


def _invoke(args):
    return CliRunner().invoke(app, args)


MODEL = """<mujoco>
  <worldbody>
    <body name="a"><joint name="ja" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 1 0 0" size="0.05" contype="0" conaffinity="0"/>
    </body>
    {extra_body}
  </worldbody>
  {extra}
</mujoco>"""


@pytest.mark.parametrize(("extra_body", "extra", "named"), [
    ("", '<equality><connect body1="a" body2="nosuch" anchor="1 0 0"/></equality>',
     "nosuch"),
    ('<body name="f"><freejoint name="float"/><geom size="0.1"/></body>', "", "float"),
    ("", '<tendon><fixed name="tt" stiffness="10"><joint joint="ja" coef="1"/></fixed>'
     "</tendon>", "tt"),
    ("", '<equality><joint name="jeq" joint1="ja"/></equality>', "jeq"),
])
def test_bad_mjcf_exit_2_names_element(tmp_path, extra_body, extra, named):
    xml = tmp_path / "bad.xml"
    xml.write_text(MODEL.format(extra_body=extra_body, extra=extra))
    r = _invoke(["import", str(xml), "--out", str(tmp_path / "bad.toml")])
    assert r.exit_code == 2, r.output
    assert str(xml) in r.output and named in r.output
    assert "Traceback" not in r.output and not (tmp_path / "bad.toml").exists()


@pytest.mark.parametrize(("extra_body", "extra", "named"), [
    ('<body name="b" pos="0 0 nan"><geom size="0.1"/></body>', "", "NaN"),
    ('<body name="b" pos="0 0 inf"><geom size="0.1"/></body>', "", "body b: body_pos"),
    ('<body name="b"><joint name="jb" axis="0 inf 1"/><geom size="0.1"/></body>', "",
     "joint jb: jnt_axis"),
    ("", '<option gravity="0 0 -inf"/>', "option: gravity"),
])
def test_mjcf_with_nan_or_inf_exit_2_and_no_mujoco_log(tmp_path, monkeypatch, extra_body,
                                                        extra, named):
    """MuJoCo only warns about a NaN (on stdout and into MUJOCO_LOG.TXT in the current
    folder) and compiles an infinity silently: both are refused, naming the element."""
    monkeypatch.chdir(tmp_path)
    xml = tmp_path / "bad.xml"
    xml.write_text(MODEL.format(extra_body=extra_body, extra=extra))
    r = _invoke(["import", str(xml), "--out", str(tmp_path / "bad.toml")])
    assert r.exit_code == 2, r.output
    assert str(xml) in r.output and named in r.output, r.output
    assert "Traceback" not in r.output and "Warning" not in r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.xml"]


def test_malformed_xml_exit_2(tmp_path):
    xml = tmp_path / "broken.xml"
    xml.write_text("<mujoco><worldbody><body name='a'></worldbody>")
    r = _invoke(["import", str(xml), "--out", str(tmp_path / "broken.toml")])
    assert r.exit_code == 2 and str(xml) in r.output and "XML" in r.output
    assert "Traceback" not in r.output


def test_existing_file_kept_without_force(tmp_path):
    out = tmp_path / "fb.toml"
    out.write_text("mine")
    r = _invoke(["import", str(CASES / "mjcf_four_bar.xml"), "--out", str(out)])
    assert r.exit_code == 2 and out.read_text() == "mine"
    r = _invoke(["import", str(CASES / "mjcf_four_bar.xml"), "--out", str(out), "--force"])
    assert r.exit_code == 0, r.output
    assert "not carried: actuator 'crank_motor'" in r.output
    text = out.read_text()
    assert "#   sensor 'crank_angle'" in text and "solref" in text
    assert load_case(out).dimension == 2


def test_weld_closes_a_loop_and_velocity_is_carried(tmp_path):
    """A weld closing a loop makes its two bodies one; a keyframe velocity is projected onto
    the loops and given through point channels that fix it (natcoord then starts with it)."""
    xml = tmp_path / "w.xml"
    xml.write_text("""<mujoco><option gravity="0 0 -9.81"/>
      <default><geom contype="0" conaffinity="0"/><joint type="hinge" axis="0 1 0"/></default>
      <worldbody>
        <body name="l"><joint name="O"/><geom type="capsule" fromto="0 0 0 0 0 1" size=".02"
            mass="1"/>
          <body name="c1" pos="0 0 1"><joint name="A"/><geom type="capsule"
            fromto="0 0 0 0.5 0 0" size=".02" mass="1"/></body></body>
        <body name="r" pos="1 0 0"><joint name="D"/><geom type="capsule" fromto="0 0 0 0 0 1"
            size=".02" mass="1"/>
          <body name="c2" pos="0 0 1"><joint name="B"/><geom type="capsule"
            fromto="0 0 0 -0.5 0 0" size=".02" mass="1"/></body></body>
      </worldbody>
      <equality><weld name="W" body1="c1" body2="c2"/></equality>
      <keyframe><key qvel="1 -1 1 -1"/></keyframe></mujoco>""")
    imp = import_mjcf(xml, "w")
    write_case(tmp_path / "w.toml", imp.text)
    case = load_case(tmp_path / "w.toml")
    assert [b.name for b in case.bodies] == ["l", "c1", "r"]  # c2 welded into c1
    assert case.body("c1").mass == 2.0
    assert len(case.velocity) == 1  # one degree of freedom: the cranks turn at 1 rad/s
    run = adapter("natcoord").run(case, initial_body_states(case), {})
    assert abs(abs(run.motion.omega["l"][0]) - 1.0) < 1e-9
    assert abs(run.motion.omega["c1"][0]) < 1e-9  # the coupler translates


@pytest.mark.parametrize("out, said", [
    ("some/dir/", "names a folder; give the case file to write"),
    ("g/x.txt", "a case file ends in .toml"),
])
def test_import_refuses_an_out_that_is_not_a_case_file(tmp_path, out, said):
    """README: --out CASE.toml. --out some/dir/ used to write a file named dir."""
    r = _invoke(["import", str(CASES / "mjcf_four_bar.xml"), "--out", f"{tmp_path}/{out}"])
    assert r.exit_code == 2, r.output
    assert f"--out '{tmp_path}/{out}': {said}" in r.output, r.output
    assert list(tmp_path.iterdir()) == []


def test_import_into_an_existing_folder_writes_the_models_case_file_there(tmp_path):
    r = _invoke(["import", str(CASES / "mjcf_four_bar.xml"), "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    assert [p.name for p in tmp_path.iterdir()] == ["mjcf_four_bar.toml"]
    assert load_case(tmp_path / "mjcf_four_bar.toml").name == "mjcf_four_bar"


def test_import_names_the_duration_option_it_cannot_take(tmp_path):
    """It used to say: generated file does not load: /tmp/natcoord-generate-XXXX/new4.toml:
    output_dt: must divide duration 0.005 s, got 0.01 s. (0.005 is below the option's
    range now, which starts at the output step: 0.015 is within it, not a multiple.)"""
    r = _invoke(["import", str(CASES / "mjcf_four_bar.xml"), "--out",
                 str(tmp_path / "new4.toml"), "--duration", "0.015"])
    assert r.exit_code == 2, r.output
    assert "--duration 0.015: must be a multiple of the output step 0.01 s" in r.output
    assert "natcoord-generate" not in r.output and list(tmp_path.iterdir()) == []


def test_a_model_file_name_with_a_newline_is_escaped_in_the_case_file(tmp_path):
    """The name went raw into # comment lines: the case file did not load."""
    xml = tmp_path / "four\nbar.xml"
    xml.write_text((CASES / "mjcf_four_bar.xml").read_text())
    out = tmp_path / "fb.toml"
    r = _invoke(["import", str(xml), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert out.read_text().startswith("# Imported by `natcoord import four\\nbar.xml --out")
    assert "four\\nbar.xml" in load_case(out).description


@pytest.mark.parametrize(("extra_body", "extra", "named"), [
    ('<body name="b"><joint name="jb"/><geom size="0.1" mass="1e300"/></body>', "",
     "body b: body_mass holds a value beyond 1e+150"),
    ("", '<option gravity="0 0 -1e200"/>', "option: gravity is beyond 1e+150"),
])
def test_mjcf_with_absurd_magnitudes_exit_2(tmp_path, extra_body, extra, named):
    """mass 1e300 imported with a numpy overflow warning, gravity 1e200 failed at run time
    with raw RuntimeWarnings: a value whose square overflows is refused, naming the element."""
    xml = tmp_path / "big.xml"
    xml.write_text(MODEL.format(extra_body=extra_body, extra=extra))
    r = _invoke(["import", str(xml), "--out", str(tmp_path / "big.toml")])
    assert r.exit_code == 2, r.output
    assert f"{xml}: {named}" in r.output, r.output
    assert "Warning" not in r.output and not (tmp_path / "big.toml").exists()


def _four_bar_xml(tmp_path, connect: str, name: str):
    """cases/mjcf_four_bar.xml with its connect named ``connect``, started turning."""
    text = (CASES / "mjcf_four_bar.xml").read_text().replace(
        '<connect name="C"', f'<connect name="{connect}"').replace(
        "</sensor>", '</sensor><keyframe><key qvel="1.0 0 0"/></keyframe>')
    xml = tmp_path / f"{name}.xml"
    xml.write_text(text)
    return xml


def test_a_connect_named_like_a_velocity_channel_starts_the_same_motion(tmp_path):
    """A connect named 'crank_A' gave the loop's position channel the name of the velocity
    channel x_crank_A (the crank's point A): the file then set the coupler point's
    velocity instead, a different motion from the same model. Channel names are unique
    now, and the assembled start is the one the connect named 'C' gives."""
    starts = {}
    for connect in ("C", "crank_A"):
        out = tmp_path / f"fb_{connect}.toml"
        r = _invoke(["import", str(_four_bar_xml(tmp_path, connect, f"fb_{connect}")),
                     "--out", str(out)])
        assert r.exit_code == 0, r.output
        case = load_case(out)
        assert len({c.name for c in case.channels}) == len(case.channels)
        init = initial_body_states(case)
        starts[connect] = {b: (init[b].velocity, init[b].omega) for b in init}
    for b, (v, w) in starts["C"].items():
        np.testing.assert_allclose(starts["crank_A"][b][0], v, atol=1e-12)
        assert starts["crank_A"][b][1] == pytest.approx(w, abs=1e-12)
    assert starts["C"]["crank"][1] != 0  # it does start turning


def test_generated_channel_names_never_clash(tmp_path):
    """A crank body named 'x' and a connect named 'theta' both made a channel theta_x: the
    file did not load ('Cannot overwrite a value'); now the second is theta_x_2."""
    out = tmp_path / "chan.toml"
    r = _invoke(["import", str(_chan_xml(tmp_path)),
                 "--out", str(out)])
    assert r.exit_code == 0, r.output
    names = [c.name for c in load_case(out).channels]
    assert "theta_x" in names and "theta_x_2" in names and len(set(names)) == len(names)


def _chan_xml(tmp_path):
    xml = tmp_path / "chan.xml"
    xml.write_text(
        '<mujoco><default><geom contype="0" conaffinity="0"/><joint type="hinge" '
        'axis="0 1 0"/></default><worldbody><body name="x"><joint name="O"/><geom '
        'type="capsule" fromto="0 0 0 0 0 1" size="0.02" mass="1"/><body name="cp" '
        'pos="0 0 1"><joint name="A"/><geom type="capsule" fromto="0 0 0 1 0 0" '
        'size="0.02" mass="1"/></body></body><body name="r" pos="1 0 0"><joint name="D"/>'
        '<geom type="capsule" fromto="0 0 0 0 0 1" size="0.02" mass="1"/></body>'
        '</worldbody><equality><connect name="theta" body1="cp" body2="r" anchor="1 0 0"/>'
        "</equality></mujoco>")
    return xml


def test_a_joint_named_like_an_added_point_keeps_its_point(tmp_path):
    """A body 'p' with a hinge named 'p_c': the point import adds to complete the body was
    named p_c too and replaced the joint's (a traceback). The pendulum's joint point is at
    the hinge, the added one at the bob."""
    xml = tmp_path / "pc.xml"
    xml.write_text('<mujoco><worldbody><body name="p"><joint name="p_c" type="hinge" '
                   'axis="0 1 0"/><geom type="sphere" size="0.1" pos="0 0 -1" mass="1" '
                   'contype="0" conaffinity="0"/></body></worldbody></mujoco>')
    out = tmp_path / "pc.toml"
    r = _invoke(["import", str(xml), "--out", str(out)])
    assert r.exit_code == 0 and "Traceback" not in r.output, r.output
    (body,) = load_case(out).bodies
    np.testing.assert_allclose(body.points["p_c"], [0.0, 0.0], atol=1e-12)
    (other,) = [k for k in body.points if k != "p_c"]
    assert np.linalg.norm(body.points[other] - body.points["p_c"]) == pytest.approx(1.0)


@pytest.mark.parametrize(("actuator", "key", "said"), [
    ('<motor name="m" joint="ja"/>', '<keyframe><key ctrl="5"/></keyframe>',
     "applies a force of 5 at the start (keyframe '0': control 5)"),
    ('<motor name="m" joint="ja" ctrllimited="true" ctrlrange="1 2"/>', "",
     "control 0, clamped to its ctrlrange [1, 2]"),
    ('<general name="m" joint="ja" dyntype="integrator"/>',
     '<keyframe><key act="4"/></keyframe>', "activation [4.0]"),
])
def test_an_actuator_that_pushes_from_the_start_is_refused(tmp_path, actuator, key, said):
    """Actuators were dropped as 'zero control: no force' whatever their control: a
    keyframe's ctrl, a ctrlrange that excludes 0 (MuJoCo clamps) or an activation."""
    xml = tmp_path / "act.xml"
    xml.write_text(MODEL.format(extra_body="", extra=f"<actuator>{actuator}</actuator>{key}"))
    r = _invoke(["import", str(xml), "--out", str(tmp_path / "act.toml")])
    assert r.exit_code == 2 and "actuator 'm'" in r.output and said in r.output, r.output
    assert not (tmp_path / "act.toml").exists()


def test_a_model_that_imports_but_cannot_start_is_refused(tmp_path):
    """A ball joint turning about its body's line: the file gave two points and two rates,
    and every run then failed; the import says so now and writes nothing."""
    xml = tmp_path / "ball.xml"
    xml.write_text('<mujoco><default><geom contype="0" conaffinity="0"/></default>'
                   '<worldbody><body name="top" pos="0 0 1"><joint name="S" type="ball"/>'
                   '<geom type="box" pos="0.2 0.1 -0.6" size="0.1 0.05 0.3" mass="1.5" '
                   'euler="5 15 25"/></body></worldbody><keyframe><key qpos="0.9 0.3 0.2 '
                   '0.1" qvel="0.5 -1.0 2.0"/></keyframe></mujoco>')
    out = tmp_path / "ball.toml"
    r = _invoke(["import", str(xml), "--out", str(out)])
    assert r.exit_code == 2 and "does not assemble" in r.output, r.output
    assert "velocity direction(s) left open" in r.output and not out.exists()


def test_a_model_path_that_is_a_folder_or_not_utf8_is_named(tmp_path):
    r = _invoke(["import", str(tmp_path), "--out", str(tmp_path / "x.toml")])
    assert r.exit_code == 2 and "a folder, not an MJCF file" in r.output, r.output
    odd = tmp_path / "c\udce9.xml"  # a byte of another encoding in the name
    odd.write_bytes((CASES / "mjcf_four_bar.xml").read_bytes())
    r = _invoke(["import", str(odd), "--out", str(tmp_path / "y.toml")])
    assert r.exit_code == 2 and "not valid UTF-8" in r.output, r.output
