"""OpenSCENARIO 1.x: files written by an independent tool (scenariogeneration's xosc API) drive
our pose source; our files validate against ASAM's XSD (shipped with scenariogeneration) and read
back through scenariogeneration's parser. Interpolation oracle: numpy lerp and scipy's Slerp."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from scube_sim.io.openscenario import read_openscenario, write_openscenario
from scube_sim.sim.sources import TrajectorySource
from scube_sim.transforms import hpr_to_rotmat, make_pose, transform_points

xosc = pytest.importorskip("scenariogeneration.xosc")

# (time, x, y, z, h, p, r): a curving, climbing, banking path
VERTS = np.array([
    [0.0, 1.0, 2.0, 0.0, 0.1, 0.0, 0.0],
    [1.0, 10.0, 3.0, 0.5, 0.3, 0.05, 0.01],
    [2.5, 20.0, 8.0, 1.0, 0.9, -0.02, 0.04],
    [4.0, 26.0, 18.0, 1.2, 1.6, 0.0, -0.03],
])
AHEAD = np.array([[2.0, 0.0, 0.0], [0.0, 1.0, 1.5]])  # body points: 2 m ahead, a roof corner


@pytest.fixture
def osc_version():
    """scenariogeneration keeps the OpenSCENARIO version as global state: put it back."""
    from scenariogeneration.xosc.enumerations import _MINOR_VERSION, VersionBase

    yield
    VersionBase().setVersion(minor=_MINOR_VERSION)


def _vehicle():
    bb = xosc.BoundingBox(2, 5, 1.8, 2.0, 0, 0.9)
    return xosc.Vehicle("car", xosc.VehicleCategory.car, bb, xosc.Axle(0.5, 0.8, 1.68, 2.98, 0.4),
                        xosc.Axle(0, 0.8, 1.68, 0, 0.4), 69, 10, 10)


def _sim_time(name, value, point="start"):
    return xosc.ValueTrigger(name, 0, xosc.ConditionEdge.none, xosc.SimulationTimeCondition(value, xosc.Rule.greaterThan),
                             point)


def _trajectory(verts=VERTS, headings=True):
    poly = xosc.Polyline(list(verts[:, 0]), [
        xosc.WorldPosition(*v[1:4], *(v[4:7] if headings else (None, None, None))) for v in verts])
    return xosc.Trajectory("egotraj", False).add_shape(poly)


def build_scenario(path: Path, minor: int = 3, *, trajectory=None, entities=("Target", "Ego"), actor="Ego",
                   domain=xosc.ReferenceContext.absolute, scale=1.0, offset=0.0, event_start=0.0, catalog=None,
                   teleport=(1.0, 2.0, 0.0, 0.1), maneuver_catalog: Path | None = None) -> Path:
    """A scenario built with scenariogeneration's API and written by it (the maneuver into a
    catalog file when `maneuver_catalog` is given)."""
    ent = xosc.Entities()
    for name in entities:
        ent.add_scenario_object(name, _vehicle())
    init = xosc.Init()
    init.add_init_action(actor, xosc.TeleportAction(xosc.WorldPosition(*teleport)))
    fta = xosc.FollowTrajectoryAction(trajectory or _trajectory(), xosc.FollowingMode.position, domain, scale, offset)
    ev = xosc.Event("ev", xosc.Priority.override if minor >= 2 else xosc.Priority.overwrite)
    ev.add_action("follow", fta)
    ev.add_trigger(_sim_time("start", event_start))
    man = xosc.Maneuver("man")
    man.add_event(ev)
    mg = xosc.ManeuverGroup("mg")
    mg.add_actor(actor)
    if maneuver_catalog is None:
        mg.add_maneuver(man)
    else:
        man.dump_to_catalog(str(maneuver_catalog), "ManCatalog", "test", "tests")
        mg.add_maneuver(xosc.CatalogReference("ManCatalog", "man"))
    act = xosc.Act("act", _sim_time("act_start", 0.0))
    act.add_maneuver_group(mg)
    story = xosc.Story("story")
    story.add_act(act)
    sb = xosc.StoryBoard(init, _sim_time("stop", 100.0, "stop"))
    sb.add_story(story)
    sce = xosc.Scenario("test", "tests", xosc.ParameterDeclarations(), ent, sb, xosc.RoadNetwork(),
                        catalog or xosc.Catalog(), osc_minor_version=minor)
    sce.write_xml(str(path))
    return path


def expected_poses(verts, times):
    """Independent interpolation: numpy lerp of positions, scipy Slerp of the ASAM rotations."""
    rots = Rotation.from_euler("ZYX", verts[:, 4:7])  # intrinsic heading, pitch, roll
    t = np.clip(times, verts[0, 0], verts[-1, 0])
    out = np.tile(np.eye(4), (len(times), 1, 1))
    out[:, :3, :3] = Slerp(verts[:, 0], rots)(t).as_matrix()
    out[:, :3, 3] = np.stack([np.interp(t, verts[:, 0], verts[:, k]) for k in (1, 2, 3)], 1)
    return out


def assert_poses_within_1mm(got, want):
    for g, w in zip(got, want):
        d = np.linalg.norm(transform_points(g, AHEAD) - transform_points(w, AHEAD), axis=1)
        assert d.max() < 1e-3, d
        assert np.linalg.norm(g[:3, 3] - w[:3, 3]) < 1e-3


# --- reading files written by scenariogeneration -------------------------------------------------

@pytest.mark.parametrize("minor", [0, 1, 2, 3])  # 1.0: Trajectory inline; 1.1+: inside TrajectoryRef
def test_scenariogeneration_file_drives_our_pose_source(tmp_path, osc_version, minor):
    path = build_scenario(tmp_path / "s.xosc", minor)
    source = TrajectorySource.from_openscenario(path)
    assert (source.t_start, source.t_end) == (0.0, 4.0)
    times = np.linspace(-0.5, 4.5, 101)  # held at both ends
    assert_poses_within_1mm(source.poses_at(times), expected_poses(VERTS, times))
    tr = read_openscenario(path)
    assert tr.entity == "Ego" and tr.entities == ["Target", "Ego"]  # 'Ego' wins over the first
    assert tr.trajectories == ["egotraj"] and tr.following_modes == ["position"]
    np.testing.assert_allclose(tr.initial_pose, make_pose(hpr_to_rotmat(0.1), [1.0, 2.0, 0.0]), atol=1e-12)


def test_trajectory_from_a_catalog_with_parameters(tmp_path, osc_version):
    (tmp_path / "catalogs").mkdir()
    traj = xosc.Trajectory("catalog_traj", False)
    traj.add_parameter(xosc.Parameter("EndX", xosc.ParameterType.double, "99"))
    verts = VERTS.copy()
    poly = xosc.Polyline(list(verts[:, 0]), [xosc.WorldPosition(*v[1:7]) for v in verts[:-1]]
                         + [xosc.WorldPosition("$EndX", *verts[-1, 2:7])])
    traj.add_shape(poly)
    traj.dump_to_catalog(str(tmp_path / "catalogs" / "trajectories.xosc"), "TrajCatalog", "test", "tests")
    cat = xosc.Catalog()
    cat.add_catalog("TrajectoryCatalog", "catalogs")  # relative to the scenario file
    ref = xosc.CatalogReference("TrajCatalog", "catalog_traj")
    ref.add_parameter_assignment("EndX", 26.0)
    path = build_scenario(tmp_path / "s.xosc", trajectory=ref, catalog=cat)
    src = TrajectorySource.from_openscenario(path)
    times = np.linspace(0, 4, 41)
    assert_poses_within_1mm(src.poses_at(times), expected_poses(VERTS, times))
    # without the assignment the catalog's default applies
    ref2 = xosc.CatalogReference("TrajCatalog", "catalog_traj")
    path2 = build_scenario(tmp_path / "s2.xosc", trajectory=ref2, catalog=cat)
    assert read_openscenario(path2).poses[-1, 0, 3] == 99.0
    # a missing entry names what the catalog has
    path3 = build_scenario(tmp_path / "s3.xosc", trajectory=xosc.CatalogReference("TrajCatalog", "nope"), catalog=cat)
    with pytest.raises(KeyError, match="no Trajectory 'nope'.*catalog_traj") as exc:
        read_openscenario(path3)
    assert str(path3) in str(exc.value)


def test_maneuver_from_a_catalog(tmp_path, osc_version):
    (tmp_path / "maneuvers").mkdir()
    cat = xosc.Catalog()
    cat.add_catalog("ManeuverCatalog", "maneuvers")
    path = build_scenario(tmp_path / "s.xosc", catalog=cat, maneuver_catalog=tmp_path / "maneuvers" / "m.xosc")
    assert "CatalogReference" in path.read_text()
    np.testing.assert_allclose(read_openscenario(path).poses[:, :3, 3], VERTS[:, 1:4])


def test_timing_scale_offset_and_the_init_teleport(tmp_path, osc_version):
    path = build_scenario(tmp_path / "s.xosc", scale=2.0, offset=1.0, teleport=(-5.0, 2.0, 0.0, 0.0))
    tr = read_openscenario(path)
    # vertex time t is reached at 2 t + 1; the Init teleport holds the ego's place at 0 s
    np.testing.assert_allclose(tr.times, np.concatenate([[0.0], 2 * VERTS[:, 0] + 1]))
    np.testing.assert_allclose(tr.poses[0, :3, 3], [-5.0, 2.0, 0.0])
    np.testing.assert_allclose(tr.poses[1:, :3, 3], VERTS[:, 1:4])


def test_relative_timing_starts_with_its_event(tmp_path, osc_version):
    path = build_scenario(tmp_path / "s.xosc", domain=xosc.ReferenceContext.relative, event_start=3.0,
                          teleport=tuple(VERTS[0, 1:5]))
    tr = read_openscenario(path)
    np.testing.assert_allclose(tr.times, np.concatenate([[0.0], VERTS[:, 0] + 3.0]))


def test_missing_heading_follows_the_path(tmp_path, osc_version):
    path = build_scenario(tmp_path / "s.xosc", trajectory=_trajectory(headings=False))
    tr = read_openscenario(path)
    d = np.diff(VERTS[:, 1:3], axis=0)
    want = np.arctan2(d[:, 1], d[:, 0])
    np.testing.assert_allclose(np.arctan2(tr.poses[:, 1, 0], tr.poses[:, 0, 0]), np.append(want, want[-1]), atol=1e-12)


def test_choosing_the_entity(tmp_path, osc_version):
    path = build_scenario(tmp_path / "s.xosc", entities=("Hero", "Target"), actor="Hero")
    assert read_openscenario(path).entity == "Hero"  # no 'Ego': the first ScenarioObject
    with pytest.raises(ValueError, match=r"'Target' follows no FollowTrajectoryAction.*entities with one: \['Hero'\]"):
        read_openscenario(path, entity="Target")
    with pytest.raises(KeyError, match=r"entity 'Bob' not found; the entities are \['Hero', 'Target'\]") as exc:
        read_openscenario(path, entity="Bob")
    assert str(path) in str(exc.value)


# --- our writer, checked by the schema and by scenariogeneration's parser ---------------------

def _our_trajectory():
    times = np.linspace(0.0, 3.0, 31)
    poses = np.stack([make_pose(hpr_to_rotmat(0.3 * t, 0.02 * np.sin(t), -0.01 * t), [5 * t, np.sin(t), 0.1 * t])
                      for t in times])
    return times, poses


@pytest.mark.parametrize("minor, xsd", [(0, "1_0"), (1, "1_1"), (2, "1_2"), (3, "1_3_1")])
def test_our_file_is_valid_against_asams_schema(tmp_path, minor, xsd):
    xmlschema = pytest.importorskip("xmlschema")
    import scenariogeneration

    schema = Path(scenariogeneration.__file__).parents[1] / "schemas" / f"OpenSCENARIO_{xsd}.xsd"
    if not schema.is_file():
        pytest.skip(f"{schema} is absent (scenariogeneration ships ASAM's XSDs there)")
    path = write_openscenario(tmp_path / "ours.xosc", *_our_trajectory(), rev_minor=minor)
    xmlschema.XMLSchema(str(schema)).validate(str(path))


def test_our_file_reads_back_through_scenariogeneration(tmp_path, osc_version):
    times, poses = _our_trajectory()
    path = write_openscenario(tmp_path / "ours.xosc", times, poses, entity="hero", following_mode="follow")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # its parser warns when the file fails the schema
        sc = xosc.ParseOpenScenario(str(path))
    assert sc.entities.scenario_objects[0].name == "hero"
    teleport = sc.storyboard.init.initactions["hero"][0].position
    fta = sc.storyboard.stories[0].acts[0].maneuvergroup[0].maneuvers[0].events[0].action[0].action
    assert fta.following_mode.get_name() == "follow"
    assert (fta.timeref.reference_domain.get_name(), fta.timeref.scale, fta.timeref.offset) == ("absolute", 1.0, 0.0)
    poly = fta.trajectory.shapes
    np.testing.assert_array_equal(poly.time, times)
    assert len(poly.positions) == len(times)
    for pos, pose in zip([teleport] + poly.positions, np.concatenate([poses[:1], poses])):
        theirs = make_pose(Rotation.from_euler("ZYX", [pos.h, pos.p, pos.r]).as_matrix(), [pos.x, pos.y, pos.z])
        np.testing.assert_allclose(theirs, pose, atol=1e-12)


def test_our_file_round_trips_through_our_source(tmp_path):
    times, poses = _our_trajectory()
    path = write_openscenario(tmp_path / "ours.xosc", times, poses)
    tr = read_openscenario(path)
    np.testing.assert_array_equal(tr.times, times)
    np.testing.assert_allclose(tr.poses, poses, atol=1e-12)
    q = np.random.default_rng(0).uniform(-1, 4, 200)
    np.testing.assert_allclose(TrajectorySource.from_openscenario(path).poses_at(q), TrajectorySource(times, poses).poses_at(q),
                               atol=1e-12)
    assert write_openscenario(tmp_path / "again.xosc", times, poses).read_bytes() == path.read_bytes()


def test_writer_refuses_bad_input_and_leaves_no_file(tmp_path):
    times, poses = _our_trajectory()
    with pytest.raises(ValueError, match="strictly increasing"):
        write_openscenario(tmp_path / "a.xosc", times[::-1], poses)
    bad = poses.copy()
    bad[3, :3, 1] *= -1  # a mirror
    with pytest.raises(ValueError, match="pose 3"):
        write_openscenario(tmp_path / "a.xosc", times, bad)
    with pytest.raises(ValueError, match="rev_minor"):
        write_openscenario(tmp_path / "a.xosc", times, poses, rev_minor=4)
    assert not list(tmp_path.iterdir())


# --- hand-written files: parameters, expressions, unsupported parts --------------------------

HAND = """<?xml version="1.0"?>
<OpenSCENARIO>
  <FileHeader revMajor="1" revMinor="2" date="2024-01-01T00:00:00" description="hand" author="tests"/>
  <ParameterDeclarations>
    <ParameterDeclaration name="EgoName" parameterType="string" value="ego"/>
    <ParameterDeclaration name="Base" parameterType="double" value="10"/>
  </ParameterDeclarations>
  <CatalogLocations/>
  <RoadNetwork/>
  <Entities><ScenarioObject name="$EgoName"/></Entities>
  <Storyboard>
    <Init><Actions/></Init>
    <Story name="s"><Act name="a">
      <ManeuverGroup name="g" maximumExecutionCount="1">
        <Actors selectTriggeringEntities="false"><EntityRef entityRef="$EgoName"/></Actors>
        <Maneuver name="m"><Event name="e" priority="override">
          <Action name="f"><PrivateAction><RoutingAction><FollowTrajectoryAction>
            <TrajectoryRef><Trajectory name="t" closed="false"><Shape>SHAPE</Shape></Trajectory></TrajectoryRef>
            TIMEREF
            <TrajectoryFollowingMode followingMode="position"/>
          </FollowTrajectoryAction></RoutingAction></PrivateAction></Action>
        </Event></Maneuver>
      </ManeuverGroup>
    </Act></Story>
  </Storyboard>
</OpenSCENARIO>
"""
POLY = """<Polyline>
  <Vertex time="0"><Position><WorldPosition x="$Base" y="0" h="0"/></Position></Vertex>
  <Vertex time="${$Base / 5}"><Position><WorldPosition x="${$Base * 2 + 1}" y="0" h="0"/></Position></Vertex>
</Polyline>"""
ABSOLUTE = '<TimeReference><Timing domainAbsoluteRelative="absolute" scale="1" offset="0"/></TimeReference>'


def _hand(tmp_path, shape=POLY, timeref=ABSOLUTE):
    path = tmp_path / "hand.xosc"
    path.write_text(HAND.replace("SHAPE", shape).replace("TIMEREF", timeref))
    return path


def test_parameters_and_expressions(tmp_path):
    tr = read_openscenario(_hand(tmp_path))
    assert tr.entity == "ego"
    np.testing.assert_array_equal(tr.times, [0.0, 2.0])
    np.testing.assert_array_equal(tr.poses[:, 0, 3], [10.0, 21.0])


@pytest.mark.parametrize("shape, timeref, message", [
    ('<Clothoid curvature="0.1" curvatureDot="0" length="10"/>', ABSOLUTE, "shape is Clothoid; only Polyline"),
    (POLY.replace('<WorldPosition x="$Base" y="0" h="0"/>', '<LanePosition roadId="1" laneId="-1" s="0"/>'),
     ABSOLUTE, "Vertex 0: the position is a LanePosition; only WorldPosition"),
    (POLY, "<TimeReference><None/></TimeReference>", "TimeReference/None"),
    (POLY.replace("$Base /", "$Nope /"), ABSOLUTE, r"unknown name '\$Nope'.*declared: \['Base', 'EgoName'\]"),
    (POLY.replace('time="0"', ""), ABSOLUTE, "Vertex 0: no 'time'"),
])
def test_unsupported_parts_are_named(tmp_path, shape, timeref, message):
    path = _hand(tmp_path, shape, timeref)
    with pytest.raises(ValueError, match=message) as exc:
        read_openscenario(path)
    assert str(path) in str(exc.value)


def test_not_openscenario(tmp_path):
    p = tmp_path / "x.xosc"
    p.write_text("<Foo/>")
    with pytest.raises(ValueError, match="<Foo>, expected <OpenSCENARIO>"):
        read_openscenario(p)
    p.write_text("<OpenSCENARIO><FileHeader")
    with pytest.raises(ValueError, match="not well-formed"):
        read_openscenario(p)
    with pytest.raises(FileNotFoundError, match="no such OpenSCENARIO file"):
        read_openscenario(tmp_path / "missing.xosc")
