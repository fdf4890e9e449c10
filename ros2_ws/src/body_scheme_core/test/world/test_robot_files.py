"""Resources a URDF names (package://, file://, relative) and URDFs whose meshes are missing."""

import os

import pytest

from body_scheme_core.world.robot_files import resolve_meshes, resolve_resource

_URDF = """<robot name="r"><link name="a"><visual><geometry><mesh filename="{uri}"/></geometry></visual>
<collision><geometry><box size="0.1 0.1 0.1"/></geometry></collision></link></robot>"""


@pytest.fixture
def tree(tmp_path, monkeypatch):
    """A workspace: src/mypkg/meshes/m.obj, an install prefix with an ament index entry for 'ament_pkg', and a URDF
    in robots/urdf/ beside robots/meshes/."""
    monkeypatch.delenv("ROS_PACKAGE_PATH", raising=False)
    monkeypatch.setenv("AMENT_PREFIX_PATH", "")
    for path in ("src/mypkg/meshes/m.obj", "prefix/share/ament_pkg/meshes/m.obj",
                 "prefix/share/ament_index/resource_index/packages/ament_pkg", "robots/meshes/m.obj",
                 "robots/urdf/local.obj"):
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / path).write_text("")
    return tmp_path


def test_package_uris_are_found_in_the_package_path_ros_package_path_ament_index_and_beside_the_urdf(tree,
                                                                                                    monkeypatch):
    """package://pkg/rest resolves through --package-path (a package or a directory of packages), then
    ROS_PACKAGE_PATH, then the ament index, then <dir>/pkg for the URDF's directory and its ancestors."""
    urdf_dir = tree / "robots" / "urdf"
    expected = str(tree / "src/mypkg/meshes/m.obj")
    assert resolve_resource("package://mypkg/meshes/m.obj", urdf_dir, [tree / "src"]) == expected
    assert resolve_resource("package://mypkg/meshes/m.obj", urdf_dir, [tree / "src/mypkg"]) == expected
    assert resolve_resource("package://mypkg/meshes/m.obj", urdf_dir) is None
    monkeypatch.setenv("ROS_PACKAGE_PATH", str(tree / "src"))
    assert resolve_resource("package://mypkg/meshes/m.obj", urdf_dir) == expected
    assert resolve_resource("package://ament_pkg/meshes/m.obj", urdf_dir) is None
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tree / "prefix"))
    assert resolve_resource("package://ament_pkg/meshes/m.obj", urdf_dir) == str(
        tree / "prefix/share/ament_pkg/meshes/m.obj")
    # pybullet_data's style: package://meshes/... with meshes/ beside the URDF's directory.
    assert resolve_resource("package://meshes/m.obj", urdf_dir) == str(tree / "robots/meshes/m.obj")


def test_file_uris_absolute_and_relative_paths(tree):
    """file:// and absolute paths are taken as they are, relative ones from the URDF's directory; http:// and
    missing files give None."""
    urdf_dir = tree / "robots" / "urdf"
    absolute = str(tree / "robots/meshes/m.obj")
    assert resolve_resource("file://" + absolute, urdf_dir) == absolute
    assert resolve_resource(absolute, urdf_dir) == absolute
    assert resolve_resource("local.obj", urdf_dir) == str(urdf_dir / "local.obj")
    assert resolve_resource("http://example.com/m.obj", urdf_dir) is None
    assert resolve_resource("file:///nonexistent/m.obj", urdf_dir) is None


def test_missing_meshes_are_dropped_and_listed_once(tree):
    """resolve_meshes makes found meshes absolute and removes the shapes whose mesh is missing, listing each URI
    once; other shapes stay."""
    text, missing = resolve_meshes(_URDF.format(uri="package://nope/m.obj") .replace("</link>", "<visual><geometry>"
                                   "<mesh filename=\"package://nope/m.obj\"/></geometry></visual></link>"),
                                   tree / "robots" / "urdf")
    assert missing == ["package://nope/m.obj"]
    assert "mesh" not in text and "box" in text
    text, missing = resolve_meshes(_URDF.format(uri="package://meshes/m.obj"), tree / "robots" / "urdf")
    assert missing == [] and os.fspath(tree / "robots/meshes/m.obj") in text
