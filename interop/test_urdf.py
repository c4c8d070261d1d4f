"""`rollbase urdf` read by an independent URDF parser (urdf_parser_py): the model's joints,
axes, limits and dimensions are the platform file's (no DDS needed; the same text is what
`--ros2` publishes on robot_description, checked in test_ros2_peers.py)."""

import tomllib

import pytest
from urdf_parser_py.urdf import URDF

from conftest import rollbase


@pytest.fixture(scope="module")
def platform(tmp_path_factory):
    out = rollbase("config", "default")
    assert out.returncode == 0, out.stderr
    p = tomllib.loads(out.stdout)
    # A platform that differs from the default where the model shows it.
    for w in p["wheels"]:
        w["lambda_max"] = round(w["lambda_max"] + 0.02, 6)
    p["wheel_radius"] = 0.1
    path = tmp_path_factory.mktemp("urdf") / "platform.toml"
    path.write_text(toml_dump(p))
    return path, p


def toml_dump(d, prefix=""):
    """A tiny TOML writer for the platform file's shapes (tables, arrays of tables, scalars)."""
    lines, tables = [], []
    for k, v in d.items():
        if isinstance(v, dict):
            tables.append((k, v))
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            tables.append((k, v))
        else:
            lines.append(f"{k} = {fmt(v)}")
    for k, v in tables:
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            lines.append(f"\n[{name}]")
            lines.append(toml_dump(v, name + "."))
        else:
            for item in v:
                lines.append(f"\n[[{name}]]")
                lines.append(toml_dump(item, name + "."))
    return "\n".join(lines)


def fmt(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(fmt(x) for x in v) + "]"
    return repr(v)


def test_the_model_is_the_platform_file(platform):
    path, p = platform
    out = rollbase("urdf", "--config", str(path))
    assert out.returncode == 0, out.stderr
    robot = URDF.from_xml_string(out.stdout.encode())
    assert robot.get_root() == "base_link"
    n = len(p["wheels"])
    for i, w in enumerate(p["wheels"], 1):
        leg = robot.joint_map[f"wheel_{i}_leg_joint"]
        assert leg.type == "prismatic" and leg.parent == "base_link"
        assert (leg.limit.lower, leg.limit.upper) == (pytest.approx(w["lambda_min"], abs=1e-6), pytest.approx(w["lambda_max"], abs=1e-6))
        assert leg.axis == [1.0, 0.0, 0.0]
        assert leg.origin.rpy[2] == pytest.approx(w["alpha"], abs=1e-6)
        assert leg.origin.xyz[2] == pytest.approx(p["wheel_radius"], abs=1e-6)
        steer = robot.joint_map[f"wheel_{i}_steer_joint"]
        assert steer.type == "continuous" and steer.axis == [0.0, 0.0, 1.0]
        # The steering joint turns back by α: its position is φ from the body x axis.
        assert steer.origin.rpy[2] == pytest.approx(-w["alpha"], abs=1e-6)
        drive = robot.joint_map[f"wheel_{i}_drive_joint"]
        assert drive.type == "continuous" and drive.axis == [0.0, 1.0, 0.0]
        wheel = robot.link_map[f"wheel_{i}_link"]
        assert wheel.visual.geometry.radius == pytest.approx(0.1)
        assert robot.get_chain("base_link", f"wheel_{i}_link", links=False) == [
            f"wheel_{i}_leg_joint", f"wheel_{i}_steer_joint", f"wheel_{i}_drive_joint"]
    assert len(robot.joints) == 3 * n


def test_custom_joint_names_and_bad_input():
    names = ",".join(f"w{i}_{k}" for i in range(1, 5) for k in ("s", "d", "l"))
    out = rollbase("urdf", "--ros2-joint-names", names)
    assert out.returncode == 0, out.stderr
    robot = URDF.from_xml_string(out.stdout.encode())
    assert sorted(j.name for j in robot.joints) == sorted(names.split(","))
    assert robot.joint_map["w1_l"].type == "prismatic" and robot.joint_map["w1_s"].axis == [0.0, 0.0, 1.0]
    bad = rollbase("urdf", "--ros2-joint-names", "a,b,c")
    assert bad.returncode != 0 and "joint names" in bad.stderr, bad.stderr
    missing = rollbase("urdf", "--config", "/nonexistent/platform.toml")
    assert missing.returncode != 0 and "platform.toml" in missing.stderr, missing.stderr
