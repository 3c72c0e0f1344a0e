"""Issue 34 item 6: every load error names the file and the element or key (and the line
of an ``.xodr`` element), and a large legitimate road loads.

Before: an ``.xodr`` with ``c="1e300"``, ``curvature="1e308"`` or ``length="1e12"`` was
refused by the live server with "the worker preparing it failed (ValueError |
OverflowError | MemoryError)", naming nothing; a YAML integer of 5 000 digits and a
``.npy`` of strings were ValueErrors the same way; a road of a million geometries was "not
prepared within 10 s" (the reader kept a 1.2 GB tree and rasterising looped over every
geometry for every sample).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from simserver.server.slot import prepare_load
from simserver.testing import CONFIGS, Client, ServerProcess

VEHICLE = CONFIGS / "vehicles" / "paper_sedan" / "vehicle.yaml"


def xodr(shape: str = "<line/>", length: str = "100", road_length: str = "100",
         elevation: str = '<elevation s="0" a="0" b="0" c="0" d="0"/>',
         width: str = '<width sOffset="0" a="3.5" b="0" c="0" d="0"/>',
         geometries: str | None = None) -> str:
    """A one-road file, one element per line: the road on line 4, the geometry on 6, its
    shape on 7, the elevation on 11, the right lane's width on 18."""
    geometry = geometries or (f'<geometry s="0" x="0" y="0" hdg="0" length="{length}">\n'
                              f"{shape}\n</geometry>")
    return "\n".join([
        '<?xml version="1.0"?>',                                    # 1
        "<OpenDRIVE>",                                              # 2
        "<header/>",                                                # 3
        f'<road id="r1" length="{road_length}" junction="-1">',     # 4
        "<planView>",                                               # 5 (geometry: 6-8)
        geometry,
        "</planView>",                                              # 9
        "<elevationProfile>",                                       # 10
        elevation,                                                  # 11
        "</elevationProfile>",                                      # 12
        "<lanes><laneSection s=\"0\">",                             # 13
        '<center><lane id="0" type="none"/></center>',              # 14
        "<right>",                                                  # 15
        '<lane id="-1" type="driving">',                            # 16
        "",                                                         # 17
        width,                                                      # 18
        "</lane>",                                                  # 19
        "</right>",
        "</laneSection></lanes>",
        "</road>",
        "</OpenDRIVE>", ""])


def scene_with(folder: Path, text: str, name: str = "road") -> Path:
    (folder / f"{name}.xodr").write_text(text)
    scene = folder / f"{name}_scene.yaml"
    scene.write_text(f"name: {name}\nvehicle: {VEHICLE}\n"
                     f"terrain: {{kind: opendrive, file: {name}.xodr, cell_m: 0.5}}\n")
    return scene


def load(folder: Path, scene: Path) -> tuple:
    """The load worker's own function, confined to the repository's configs and ``folder``
    (as a server with ``config_dirs: [configs, folder]``)."""
    return prepare_load(str(scene), None, scene, (CONFIGS, folder), str(folder), folder)


XODR_CASES = [
    # the three: a cubic's coefficient, an arc's curvature, a geometry's length
    ("poly3 c", xodr(shape='<poly3 a="0" b="0" c="1e300" d="0"/>'), 7,
     "road r1 <geometry> #0 <poly3>", "attribute 'c'"),
    ("arc curvature", xodr(shape='<arc curvature="1e308"/>'), 7,
     "road r1 <geometry> #0 <arc>", "attribute 'curvature'"),
    ("geometry length", xodr(length="1e12"), 6, "road r1 <geometry> #0",
     "attribute 'length'"),
    ("road length", xodr(road_length="1e12"), 4, "road r1", "attribute 'length'"),
    ("elevation c", xodr(elevation='<elevation s="0" a="0" b="0" c="1e300" d="0"/>'), 11,
     "road r1 <elevation> #0", "attribute 'c'"),
    ("width d", xodr(width='<width sOffset="0" a="3.5" b="0" c="0" d="1e200"/>'), 18,
     "road r1 <laneSection> #0 <right> lane -1 <width> #0", "attribute 'd'"),
    ("paramPoly3 bV", xodr(shape='<paramPoly3 aU="0" bU="1" cU="0" dU="0" aV="0" bV="1e300" '
                                 'cV="0" dV="0" pRange="normalized"/>'), 7,
     "road r1 <geometry> #0 <paramPoly3>", "attribute 'bV'"),
]


@pytest.mark.parametrize("name, text, line, element, attribute", XODR_CASES,
                         ids=[c[0] for c in XODR_CASES])
def test_an_xodr_number_out_of_bounds_names_file_line_element_and_attribute(
        tmp_path, name, text, line, element, attribute):
    result = load(tmp_path, scene_with(tmp_path, text))
    assert result[0] == "error" and result[1] == "scene", result
    assert f"road.xodr:{line}: {element}: {attribute}=" in result[2], result[2]
    assert str(tmp_path) not in result[2]  # shown relative to the config folder


def test_xodr_syntax_errors_and_order_name_the_line(tmp_path):
    text = xodr()
    broken = text.replace("</lane>", "</lanes>", 1)  # line 19
    result = load(tmp_path, scene_with(tmp_path, broken))
    assert result[0] == "error" and "road.xodr:19: unreadable XML (mismatched tag" \
        in result[2], result
    two = ('<geometry s="50" x="50" y="0" hdg="0" length="50">\n<line/>\n</geometry>\n'
           '<geometry s="0" x="0" y="0" hdg="0" length="50">\n<line/>\n</geometry>')
    result = load(tmp_path, scene_with(tmp_path, xodr(geometries=two)))
    assert result[0] == "error" and "road.xodr:9: road r1 <geometry> #1: s=0 comes before" \
        in result[2], result[2]
    # and the good file loads
    result = load(tmp_path, scene_with(tmp_path, xodr()))
    assert result[0] == "ok", result


def test_roads_spanning_too_many_cells_are_refused_naming_the_file(tmp_path):
    """Two geometries 100 km apart diagonally: 4e10 cells of 0.5 m (was a MemoryError
    allocating them)."""
    two = ('<geometry s="0" x="0" y="0" hdg="0" length="10">\n<line/>\n</geometry>\n'
           '<geometry s="10" x="100000" y="100000" hdg="0" length="10">\n<line/>\n'
           '</geometry>')
    result = load(tmp_path, scene_with(tmp_path, xodr(geometries=two, road_length="20")))
    assert result[0] == "error" and "road.xodr: the roads span" in result[2], result
    assert "more than 40000000" in result[2]


def test_other_files_of_a_load_name_the_file_and_key(tmp_path):
    """A YAML integer of 5 000 digits (Python refuses to convert it) and a height map of
    strings were ValueErrors that named nothing."""
    scene = tmp_path / "digits.yaml"
    scene.write_text(f"name: digits\nvehicle: {VEHICLE}\ninitial: {{u_mps: {'9' * 5000}}}\n")
    result = load(tmp_path, scene)
    assert result[0] == "error" and re.search(
        r"digits.yaml: not valid YAML: an integer of 5000 characters .*\(line 3, column 18\)",
        result[2]), result
    np.save(tmp_path / "words.npy", np.array([["a", "b"], ["c", "d"]]))
    scene = tmp_path / "words.yaml"
    scene.write_text(f"name: words\nvehicle: {VEHICLE}\n"
                     "terrain: {kind: heightmap, file: words.npy, cell_m: 1.0}\n")
    result = load(tmp_path, scene)
    assert result[0] == "error" and "words.npy: terrain.file: an array of <U1 values, " \
        "expected real numbers" in result[2], result


def big_road(path: Path, n: int, piece_m: float) -> None:
    """One straight road of ``n`` line geometries of ``piece_m`` each (about 90 bytes a
    geometry: 1e6 of them make 90 MB)."""
    with open(path, "w") as f:
        f.write(f'<?xml version="1.0"?>\n<OpenDRIVE>\n<header/>\n'
                f'<road id="1" length="{n * piece_m:.4f}" junction="-1">\n<planView>\n')
        for k in range(n):
            f.write(f'<geometry s="{k * piece_m:.4f}" x="{k * piece_m:.4f}" y="0.0" '
                    f'hdg="0.0" length="{piece_m}"><line/></geometry>\n')
        f.write('</planView>\n<lanes><laneSection s="0"><center><lane id="0" type="none"/>'
                '</center><right><lane id="-1" type="driving"><width sOffset="0" a="3.5" '
                'b="0" c="0" d="0"/></lane></right></laneSection></lanes>\n</road>\n'
                '</OpenDRIVE>\n')


def test_the_live_server_names_the_element_and_loads_a_road_of_a_million_geometries(
        tmp_path):
    """Through ``ctl/load`` and the server's worker process: the issue's three files are
    refused with file, line, element and attribute (was "the worker preparing it failed
    (...)"), and a 20 km road of 10^6 geometries (90 MB) loads: the worker reports its
    progress and the load is abandoned only when that stops (``load_stall_s``), not after
    10 s (the server logs the progress)."""
    for name, shape, length in (("c", '<poly3 a="0" b="0" c="1e300" d="0"/>', "100"),
                                ("curvature", '<arc curvature="1e308"/>', "100"),
                                ("length", "<line/>", "1e12")):
        scene_with(tmp_path, xodr(shape=shape, length=length), name)
    big_road(tmp_path / "big.xodr", 1_000_000, 0.02)
    assert (tmp_path / "big.xodr").stat().st_size > 80e6
    big = tmp_path / "big_scene.yaml"
    big.write_text(f"name: big\nvehicle: {VEHICLE}\n"
                   "terrain: {kind: opendrive, file: big.xodr, cell_m: 0.5}\n"
                   "start: {road: '1', s: 10000.0, lane: -1}\n")
    config = tmp_path / "server.yaml"
    config.write_text(f"scene: {CONFIGS / 'scenes' / 'flat_paper_sedan.yaml'}\n"
                      f"config_dirs: [{CONFIGS}, {tmp_path}]\nviewer: 'off'\n")
    with ServerProcess(config=config) as server:
        client = Client(server)
        try:
            client.wait_controls()
            expected = {"c": "c.xodr:7: road r1 <geometry> #0 <poly3>: attribute 'c'=",
                        "curvature": "curvature.xodr:7: road r1 <geometry> #0 <arc>: "
                                     "attribute 'curvature'=",
                        "length": "length.xodr:6: road r1 <geometry> #0: attribute 'length'="}
            for name, needle in expected.items():
                reply = client.request("load", {"scene": f"{name}_scene.yaml"}, timeout_s=60.0)
                assert reply["ok"] is False and reply["field"] == "scene", reply
                assert needle in reply["error"], reply
            reply = client.request("load", {"scene": "big_scene.yaml"}, timeout_s=280.0)
            assert reply["ok"] is True, (reply, server.text()[-3000:])
            assert reply["scene"] == "big_scene.yaml"
            state = client.fresh_state(timeout_s=10.0)
            assert abs(state["x_m"] - 10000.0) < 5.0  # on the big road, 10 km along it
        finally:
            client.close()
        assert "control load: preparing for" in server.text()  # its progress, logged
