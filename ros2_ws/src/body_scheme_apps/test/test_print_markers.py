"""print_markers: the sheet of a marker file written by hand, a plate of several tags on one piece."""

from body_scheme_apps.print_markers import main

PLATE = """
- {id: 1, link: base, size: 0.1}
- {id: 20, link: tool0, xyz: [0.0, 0.0, 0.02], rpy: [0, 0, 0], size: 0.06, plate: 20}
- {id: 21, link: tool0, xyz: [0.075, 0.0, 0.02], rpy: [0, 0, 0], size: 0.06, plate: 20}
"""


def test_a_hand_written_file_with_a_plate_prints_beside_it(tmp_path, capsys):
    path = tmp_path / "my.markers.yaml"
    path.write_text(PLATE)
    assert main([str(path), "--dpi", "150"]) == 0
    assert (tmp_path / "my.markers.pdf").is_file() and (tmp_path / "my.markers.png").is_file()
    assert "print at actual size" in capsys.readouterr().out


def test_a_bad_file_is_one_line_and_exit_1(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text("- {id: 20, link: tool0, plate: 5}\n")  # a plate named after none of its markers
    assert main([str(path)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("print_markers: ") and "plate 5" in err and err.count("\n") == 1
    assert main([str(tmp_path / "missing.yaml")]) == 1
