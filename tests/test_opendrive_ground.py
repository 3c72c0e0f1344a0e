"""The ground an OpenDRIVE terrain generates off its lanes (issue 34 item 2).

The standard describes no ground between or beyond the roads; ``rasterise`` fills it with
the harmonic interpolation of the lanes' surface (docs/model.md section 11): continuous,
no cliff where the standard describes none. Before, each cell took the nearest surface
cell along its grid row or column: on esmini's ``tunnels.xodr`` (``tests/data``) 5 389
pairs of neighbouring cells differed by over 1 m, the largest by 12.01 m.
"""

from __future__ import annotations

import numpy as np
import pytest

from simserver.adapters.opendrive import load_opendrive, rasterise
from simserver.testing import REPO

pytestmark = pytest.mark.timeout(300)

TUNNELS = REPO / "tests" / "data" / "tunnels.xodr"


def neighbour_steps(heights: np.ndarray) -> np.ndarray:
    """The height differences of every pair of neighbouring cells (m)."""
    return np.concatenate([np.abs(np.diff(heights, axis=1)).ravel(),
                           np.abs(np.diff(heights, axis=0)).ravel()])


def test_the_ground_between_the_roads_of_tunnels_xodr_has_no_cliff():
    heights, _, _ = rasterise(load_opendrive(TUNNELS), 0.5, 20.0)
    steps = neighbour_steps(heights)
    print(f"\ntunnels.xodr at 0.5 m: {int((steps > 1.0).sum())} steps over 1 m between "
          f"neighbouring cells, largest {steps.max():.2f} m (before: 5 389, 12.01 m)")
    # the roads rise up to 20 m at grades of a few per cent, tens of metres apart: the
    # smoothest ground between them climbs well under a metre per 0.5 m cell
    assert (steps > 1.0).sum() == 0
    assert steps.max() < 0.5


def _parallel_roads(tmp_path, gap_m: float, rise_m: float, length_m: float = 400.0):
    """Two straight level roads along x, one lane of 3 m each side, the second ``gap_m``
    to the left of the first and ``rise_m`` higher."""
    def road(rid: str, y: float, z: float) -> str:
        return (f'<road id="{rid}" length="{length_m}" junction="-1"><planView>'
                f'<geometry s="0" x="0" y="{y}" hdg="0" length="{length_m}"><line/></geometry>'
                f'</planView><elevationProfile><elevation s="0" a="{z}" b="0" c="0" d="0"/>'
                '</elevationProfile><lanes><laneSection s="0">'
                '<left><lane id="1" type="driving"><width sOffset="0" a="3" b="0" c="0" d="0"/>'
                '</lane></left><center><lane id="0" type="none"/></center>'
                '<right><lane id="-1" type="driving"><width sOffset="0" a="3" b="0" c="0" '
                'd="0"/></lane></right></laneSection></lanes></road>')

    path = tmp_path / "parallel.xodr"
    path.write_text('<?xml version="1.0"?><OpenDRIVE><header revMajor="1" revMinor="6"/>'
                    + road("1", 0.0, 0.0) + road("2", gap_m, rise_m) + "</OpenDRIVE>",
                    encoding="utf-8")
    return path


def test_the_ground_between_two_parallel_roads_is_the_harmonic_ramp(tmp_path):
    """Laplace's equation between two long parallel edges held at 0 and 10 m is a straight
    ramp across the gap (the ends' influence decays as exp(-pi d / gap): nil 200 m from
    them), and beyond the outer edges, with no slope across the grid's border, it is flat
    at the edge's height."""
    gap, rise, cell = 40.0, 10.0, 0.5
    heights, x0, y0 = rasterise(load_opendrive(_parallel_roads(tmp_path, gap, rise)), cell,
                                20.0)
    column = heights[:, int(round((200.0 - x0) / cell))]
    y = y0 + cell * np.arange(column.size)
    edge_low, edge_high = 3.0, gap - 3.0  # the lanes' outer edges facing each other
    between = (y > edge_low + cell) & (y < edge_high - cell)
    ramp = rise * (y[between] - edge_low) / (edge_high - edge_low)
    # the edge is where the lane's last sample lands: within half a cell of 3 m, so the
    # ramp's ends shift by up to cell / 2 / 34 m x 10 m = 0.07 m
    assert np.abs(column[between] - ramp).max() < 0.1
    assert np.abs(column[y < -3.0 - cell] - 0.0).max() < 0.01
    assert np.abs(column[y > gap + 3.0 + cell] - rise).max() < 0.01


# ---------------------------------------------------------------- what the reader drops
def test_every_dropped_element_of_tunnels_xodr_is_reported_once_with_its_lines(caplog):
    """Objects and tunnels were dropped without a word; now one line per element name,
    with the lines it is on (found here independently, by the text), logged once when
    the terrain loads."""
    import logging

    from simserver.adapters.terrain_files import terrain_from_spec

    text = TUNNELS.read_text(encoding="utf-8").splitlines()
    lines_of = {tag: [n for n, line in enumerate(text, 1) if f"<{tag} " in line]
                for tag in ("object", "tunnel")}
    assert len(lines_of["object"]) == 3 and len(lines_of["tunnel"]) == 4
    dropped = load_opendrive(TUNNELS).dropped
    assert len(dropped) == 2
    for tag, at in lines_of.items():
        (line,) = [d for d in dropped if f"<{tag}>" in d]
        assert line.startswith("tunnels.xodr: ") and ", ".join(map(str, at)) in line
    caplog.set_level(logging.WARNING, logger="simserver.terrain")
    terrain_from_spec({"kind": "opendrive", "file": str(TUNNELS), "cell_m": 1.0,
                       "margin_m": 5.0})
    warned = [r.getMessage() for r in caplog.records if r.name == "simserver.terrain"]
    assert warned == list(dropped)


def test_lane_heights_signals_and_offsets_are_reported_and_metadata_is_not(tmp_path):
    """A kerb of 12 cm (a lane ``<height>``), a signal and a lane offset: each reported with
    its line; the header, links and road marks' patterns are not (they do not shape the
    ground)."""
    path = tmp_path / "kerb.xodr"
    path.write_text("\n".join((
        '<?xml version="1.0"?>',
        '<OpenDRIVE><header revMajor="1" revMinor="6"><geoReference>x</geoReference></header>',
        '<road id="1" length="50" junction="-1"><link><successor elementType="road" '
        'elementId="2"/></link>',
        '<planView><geometry s="0" x="0" y="0" hdg="0" length="50"><line/></geometry>'
        '</planView>',
        '<lanes><laneOffset s="0" a="0.5" b="0" c="0" d="0"/><laneSection s="0">',
        '<center><lane id="0" type="none"><roadMark sOffset="0" type="broken">'
        '<type name="b"><line length="3" space="9"/></type></roadMark></lane></center>',
        '<right><lane id="-1" type="driving"><width sOffset="0" a="3.5" b="0" c="0" d="0"/>'
        '</lane>',
        '<lane id="-2" type="sidewalk"><width sOffset="0" a="2" b="0" c="0" d="0"/>',
        '<height sOffset="0" inner="0.12" outer="0.12"/></lane></right>',
        '</laneSection></lanes>',
        '<signals><signal s="10" t="-4" id="9" type="206"/></signals></road></OpenDRIVE>',
    )), encoding="utf-8")
    dropped = load_opendrive(path).dropped
    assert [d.split(" dropped")[0] for d in dropped] == [
        "kerb.xodr: <laneOffset>", "kerb.xodr: <height>", "kerb.xodr: <signal>"]
    assert "(line 5)" in dropped[0] and "(line 9)" in dropped[1] and "(line 11)" in dropped[2]
    assert "lane heights (kerbs, sidewalks) are not applied" in dropped[1]
