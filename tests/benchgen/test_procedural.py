"""The procedural scene family (``benchgen generate --random``): determinism, plausibility, the
cases it must contain, the lathe part it uses, the splits, and a small real render."""

from __future__ import annotations

import numpy as np
import pytest

from scenecore import dataset as D
from benchgen.cli import main as cli_main
from benchgen.scene import procedural as P
from benchgen.scene.geometry import build_scene, part_contains, part_mesh
from benchgen.scene.plausibility import check_authored_scene
from benchgen.scene.spec import Part, SpecError, dump_spec, load_spec, spec_from_dict

#: Development seeds the tests draw (the held-out split is for reporting only).
SEEDS = range(0, 8)


@pytest.fixture(scope="module")
def family():
    return {s: P.random_spec(s) for s in SEEDS}


def test_a_seed_gives_the_same_scene_and_seeds_differ(family):
    assert dump_spec(P.random_spec(3)) == dump_spec(family[3])
    assert len({dump_spec(s) for s in family.values()}) == len(family)
    stereo = P.random_spec(3, "stereo")
    assert stereo.rig.protocol == "stereo" and dump_spec(P.random_spec(3, "stereo")) == dump_spec(stereo)
    assert P.random_spec(3, "multi-camera").rig.protocol == "multi-camera"


def test_every_scene_is_plausible_in_view_and_has_the_cases_the_family_promises(family):
    counts = []
    floor_movers = 0
    types = set()
    for seed, spec in family.items():
        built = build_scene(spec)
        check_authored_scene(built)  # inside the room, no interpenetration, no camera inside an object
        assert P._family_problem(spec, [True]) is None, seed
        counts.append(len(spec.objects))
        for o in spec.objects:
            types |= {p.type for p in o.parts}
            z = [k.location[2] for k in o.keyframes]
            if all(abs(v) < 1e-12 for v in z):
                floor_movers += 1
                # A floor mover's base touches the floor at every time: the contact case.
                g = next(g for g in built.objects if g.name == o.name)
                poses = built.scene.objects[[x.name for x in built.scene.objects].index(o.name)].poses
                lows = [(g.mesh.vertices @ T[:3, :3].T + T[:3, 3])[:, 2].min() for T in poses]
                assert np.allclose(lows, 0.0, atol=1e-9), (seed, o.name)
    assert min(counts) >= P.MOVERS[0] and max(counts) <= P.MOVERS[1] and len(set(counts)) >= 3
    # A pair passing in front of another in every scene: _family_problem returned None above, and it
    # refuses a scene without one (test_a_draw_without_a_floor_mover_or_a_crossing_is_refused).
    assert floor_movers >= len(family)
    assert {"lathe", "torus", "box", "cylinder"} <= types


def test_a_draw_without_a_floor_mover_or_a_crossing_is_refused(family):
    spec = family[0]
    assert P._family_problem(spec, [False] * len(spec.objects)) == "no mover on the floor"
    apart = spec_from_dict({**spec.to_dict(), "objects": spec.to_dict()["objects"][:1]}, "one mover")
    assert P._family_problem(apart, [True]) == "no pair of movers passes in front of another"


def test_the_splits_are_disjoint_and_seeds_parse():
    assert P.split_of(0) == P.split_of(999) == "development" and P.split_of(1000) == P.split_of(1999) == "held-out"
    assert P.split_of(5000) == "unassigned"
    assert not set(P.SPLITS["development"]) & set(P.SPLITS["held-out"])
    assert P.parse_seeds("3:6,9") == [3, 4, 5, 9]
    for bad in ("6:3", "a", "-1"):
        with pytest.raises(ValueError):
            P.parse_seeds(bad)


def test_lathe_parts_are_checked_and_their_solid_matches_their_mesh():
    cup = [[0, 0], [0.2, 0], [0.2, 0.3], [0.18, 0.3], [0.18, 0.02], [0, 0.02]]
    washer = [[0.1, 0], [0.2, 0], [0.2, 0.05], [0.1, 0.05]]
    rng = np.random.default_rng(0)
    for profile in (cup, washer):
        part = Part("lathe", {"profile": profile})
        mesh = part_mesh(part)
        assert mesh.is_watertight
        lo, hi = mesh.bounds
        pts = rng.uniform(lo, hi, (200_000, 3))
        # The analytic inside test and the rendered mesh enclose the same volume (to Monte Carlo error).
        assert part_contains(part, pts).mean() * np.prod(hi - lo) == pytest.approx(mesh.volume, rel=0.03)
    assert part_contains(Part("lathe", {"profile": washer}), np.array([[0, 0, 0.02], [0.15, 0, 0.02]])).tolist() == [False, True]
    base = {"name": "x", "room": {"size": [4, 4, 3]}, "objects": [{"name": "a", "motion": [{"t": 0, "location": [0, 0, 0]}]}]}
    for profile, message in (([[0, 0], [1, 1]], "3 to"), ([[-0.1, 0], [1, 0], [1, 1]], "radius must be >= 0"),
                             ([[0, 0], [2, 2], [2, 0], [0, 1]], "cross"), ([[0, 0], [1, 0], [2, 0]], "no area")):
        base["objects"][0]["parts"] = [{"type": "lathe", "profile": profile}]
        with pytest.raises(SpecError, match=message):
            spec_from_dict(base, "s.yaml")


def test_the_command_line_refuses_mixed_sources(tmp_path, capsys):
    for args in (["generate", "--random", "1", "--preset", "tiny", "--out", str(tmp_path / "a")],
                 ["generate", "--preset", "tiny", "--protocol", "stereo", "--out", str(tmp_path / "a")],
                 ["generate", "--random", "1:3", "--out", str(tmp_path / "a")],
                 ["generate", "--random", "x", "--out", str(tmp_path / "a")],
                 ["suite", "--random", "5:2", "--out", str(tmp_path / "b")],
                 ["suite", "--random", "1:2", "--presets", "gnome-house", "--out", str(tmp_path / "b")]):
        assert cli_main(args) == 2
        assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


@pytest.mark.slow
def test_a_random_scene_renders_verifies_and_reruns_from_its_spec(tmp_path, capsys):
    out = tmp_path / "suite"
    assert cli_main(["suite", "--random", "4", "--out", str(out), "--resolution", "32", "--configs", "2", "--quiet"]) == 0
    assert "| random-4 | orbit |" in capsys.readouterr().out
    data = out / "random-4"
    scene = D.load_scene(data)
    assert D.load_verification(data)["passed"]
    # Every mover is seen in the rendered video, occlusions included, most of the time: in at least
    # half the frames it shows half of the family's MIN_PIXELS at this resolution (a quarter of
    # 64 px's pixels), and in some frame what osn oracle needs (16 pixels at 64 px: 4 here).
    enough = np.zeros(scene.num_objects)
    most = np.zeros(scene.num_objects)
    for f in scene.train_frames:
        counts = np.bincount(D.read_ids(D.frame_paths(data, f.name).ids).ravel(), minlength=256)[: scene.num_objects]
        enough += counts >= P.MIN_PIXELS / 4 / 2
        most = np.maximum(most, counts)
    assert np.all(enough[1:] >= 0.5 * len(scene.train_frames)), enough
    assert np.all(most[1:] >= 4), most
    # The dataset's spec.yaml is the scene: rerunning from it renders nothing new.
    assert dump_spec(load_spec(data / "spec.yaml")) == (data / "spec.yaml").read_text()
    assert cli_main(["generate", "--spec", str(data / "spec.yaml"), "--out", str(data), "--quiet"]) == 0
    assert "rendered 0 frames" in capsys.readouterr().out


@pytest.mark.slow
@pytest.mark.parametrize("protocol", ["stereo", "multi-camera"])
def test_random_scenes_of_the_other_protocols_render_and_verify(tmp_path, protocol):
    out = tmp_path / protocol
    args = ["generate", "--random", "5", "--protocol", protocol, "--out", str(out), "--resolution", "32", "--configs", "2", "--quiet"]
    assert cli_main(args) == 0
    assert D.load_verification(out)["passed"]
    assert load_spec(out / "spec.yaml").rig.protocol == protocol


def test_visible_pixels_count_what_no_other_mover_hides():
    """A mover wholly behind another shows nothing, even through the gaps between the front one's
    points; side by side both show their whole footprint."""
    K = np.array([[64.0, 0, 32], [0, 64.0, 32], [0, 0, 1]])
    c2w = np.eye(4)  # OpenCV camera at the origin looking down +z
    grid = np.stack(np.meshgrid(np.linspace(-0.1, 0.1, 40), np.linspace(-0.1, 0.1, 40)), -1).reshape(-1, 2)
    front = np.c_[grid, np.full(len(grid), 1.0)]  # ~13 px square at depth 1 (points 1/3 px apart)
    sparse = front[::3]  # the same square with gaps between its points
    behind = np.c_[grid * 1.5, np.full(len(grid), 1.5)]  # the same footprint further away
    aside = behind + [0.6, 0.0, 0.0]
    assert P.visible_pixels([front, behind], c2w, K)[1] == 0
    assert P.visible_pixels([sparse, behind], c2w, K)[1] == 0
    a, b = P.visible_pixels([front, aside], c2w, K)
    assert a == P.visible_pixels([front], c2w, K)[0] > 100 and b == P.visible_pixels([aside], c2w, K)[0] > 100
