"""OpenSCENARIO: the storyboard's own rules and the transitions not covered by
tests/test_openscenario.py (issue 31 acceptance: "every condition and transition shape of
the subset each have a test on a small hand-written .xosc whose expected outcome is
computed by hand"; docs/openscenario.md).

- The reader's own structural checks (the ASAM XSD is not shipped): a storyboard element
  reference, a distance kind, a boolean and a child element the subset does not know are
  errors naming file, line and element, never dropped silently.
- Played with physical cars: condition edges (rising with a delay, falling,
  risingOrFalling, none with a delay), OR over AND groups, an event's priority (overwrite,
  skip, parallel) and maximumExecutionCount, StoryboardElementStateCondition,
  AccelerationCondition, StandStillCondition; the speed transitions sinusoidal over time,
  linear over distance, cubic over rate, step; lane changes linear over rate, sinusoidal
  over distance, step.
- ``simserver run-scenario FILE.xosc`` as a real subprocess: the storyboard trace file.
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from simserver.adapters.openscenario import XoscError, load_openscenario

from tests.test_openscenario import (
    _at_time,
    _by_entity,
    _speed,
    _story,
    expect_error,
    line_of,
    speed_event,
    write,
)

REPO = Path(__file__).resolve().parents[1]
ROAD = (REPO / "configs/openscenario/xodr/straight_500m.xodr").as_posix()
LANE_WIDTH_M = 3.07  # lanes 1 and -1 of straight_500m.xodr (its <width a=...>)
TICK_S = 0.01  # the storyboard's period (xosc_run.STORYBOARD_PERIOD_S)
TIME_COND = ('<Condition name="c" delay="0" conditionEdge="rising"><ByValueCondition>'
             '<SimulationTimeCondition value="1" rule="greaterThan"/></ByValueCondition>'
             '</Condition>')


# ------------------------------------------------------------------ the reader's own checks
def _state_cond(kind: str, ref: str, state: str = "completeState") -> str:
    return ('<Condition name="c" delay="0" conditionEdge="rising"><ByValueCondition>\n'
            f'<StoryboardElementStateCondition storyboardElementType="{kind}" '
            f'storyboardElementRef="{ref}" state="{state}"/></ByValueCondition></Condition>')


def test_storyboard_element_reference_is_checked_when_read(tmp_path: Path) -> None:
    """A StoryboardElementStateCondition naming no element of the storyboard is an error
    when the file is read (before: only when the player first evaluated it, mid-run), as
    is an element type outside the schema's; a reference to an element further down the
    file is fine."""
    ok = write(tmp_path, speed_event("1", _state_cond("event", "E")))
    assert load_openscenario(ok).stories[0].acts[0].groups[0].maneuvers[0].events[0].start
    path = write(tmp_path, speed_event("1", _state_cond("event", "NoSuchEvent")))
    expect_error(path, line_of(path, "NoSuchEvent"), "StoryboardElementStateCondition",
                 "no event named 'NoSuchEvent'")
    path = write(tmp_path, speed_event("1", _state_cond("action", "E")))
    expect_error(path, line_of(path, 'storyboardElementRef="E"'),
                 "StoryboardElementStateCondition", "no action named 'E'")
    path = write(tmp_path, speed_event("1", _state_cond("scene", "E")))
    expect_error(path, line_of(path, '"scene"'), "StoryboardElementStateCondition",
                 "'scene' is not one of")


def _distance_cond(attrs: str, tag: str = "RelativeDistanceCondition") -> str:
    return _by_entity("A", f'\n<{tag} entityRef="B" value="10" rule="lessThan" {attrs}/>')


@pytest.mark.parametrize(("tag", "attrs", "message"), [
    ("RelativeDistanceCondition", 'freespace="false" relativeDistanceType="longitudnal"',
     "'longitudnal' is not one of"),
    ("RelativeDistanceCondition", 'freespace="true" relativeDistanceType="lateral"',
     "freespace distance 'lateral' outside the subset refused"),
    ("RelativeDistanceCondition", 'freespace="yes" relativeDistanceType="longitudinal"',
     "'yes' is not a boolean"),
    ("RelativeDistanceCondition", 'freespace="false" relativeDistanceType="longitudinal" '
     'coordinateSystem="trajectory"', "trajectories are not supported"),
    ("TimeHeadwayCondition", 'freespace="true" alongRoute="true" '
     'relativeDistanceType="lateral"', "headway and time to collision are measured"),
])
def test_a_distance_the_player_would_not_measure_is_an_error(
        tmp_path: Path, tag: str, attrs: str, message: str) -> None:
    """Before, a misspelt relativeDistanceType was measured as the cartesian distance, a
    lateral freespace distance as the centre-to-centre one, a freespace="yes" as false:
    each a condition other than the file's, silently."""
    path = write(tmp_path, speed_event("1", _distance_cond(attrs, tag)))
    expect_error(path, line_of(path, f"<{tag} "), tag, message)


def test_a_boolean_spelt_1_is_true(tmp_path: Path) -> None:
    path = write(tmp_path, speed_event("1", _distance_cond(
        'freespace="1" relativeDistanceType="longitudinal"')))
    cond = load_openscenario(path).stories[0].acts[0].groups[0].maneuvers[0].events[0] \
        .start[0][0]
    assert cond.values["freespace"] == "true"


@pytest.mark.parametrize(("before", "after", "element"), [
    ('<Maneuver name="M">', '<Maneuvr name="M2"/><Maneuver name="M">', "Maneuvr"),
    ('<Event name="E"', '<Evnt name="E2"/><Event name="E"', "Evnt"),
    ('<Action name="act">', '<Acton name="x"/><Action name="act">', "Acton"),
    ('<StartTrigger><ConditionGroup><Condition name="go"',
     '<StopTriger/><StartTrigger><ConditionGroup><Condition name="go"', "StopTriger"),
    ('<Act name="Act">', '<Actt name="x"/><Act name="Act">', "Actt"),
])
def test_an_unknown_child_of_the_storyboard_is_refused_not_dropped(
        tmp_path: Path, before: str, after: str, element: str) -> None:
    """A child element the subset does not read inside Story, Act, ManeuverGroup,
    Maneuver or Event (a misspelt one) was skipped silently: the scenario played without
    it. Now it is refused by file, line and name (docs/openscenario.md: never silently
    dropped)."""
    body = speed_event("1", TIME_COND).replace(before, "\n" + after, 1)
    path = write(tmp_path, body)
    expect_error(path, line_of(path, f"<{element}"), element,
                 "element outside the subset refused")


def test_select_triggering_entities_true_is_refused(tmp_path: Path) -> None:
    """``selectTriggeringEntities="true"`` makes the triggering entities the actors; the
    player does not, so the file is refused (before: read as false, silently)."""
    body = speed_event("1", TIME_COND).replace('selectTriggeringEntities="false"',
                                                'selectTriggeringEntities="true"')
    path = write(tmp_path, body)
    expect_error(path, line_of(path, "selectTriggeringEntities"), "Actors",
                 "selectTriggeringEntities 'true' outside the subset refused")
