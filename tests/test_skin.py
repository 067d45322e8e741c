"""The detection skin (engine.contact.skin) finds, at every step, exactly the contacts a full
detection finds: the same keys, points, normals, gaps, tags and candidate planes, compared
step by step on short runs of the rock masses, the piles and examples."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from engine.contact import search as contact_search
from engine.contact.skin import Skin, skin_margin
from engine.model import Model
from engine.step import stepping
from engine.step.simulation import Simulation
from tests.digest_cases import CASES


def _rock_mass(spacing: float) -> Model:
    from benchmarks.pile import rock_mass_model

    return rock_mass_model(spacing, duration=1.0)


def _pile(n: int) -> Model:
    from benchmarks.pile import pile_model

    return pile_model(n, duration=2.0)


def _compare_steps(model: Model, steps: int) -> Skin:
    """Step `model` `steps` times; before each step, the skin's contacts and a full
    detection's must be the same array for array. Returns the run's skin."""
    sim = Simulation(model)
    for _ in range(steps):
        system, state = sim.system, sim.state
        reach = stepping.reach(system, state, stepping.first_attempt(system, state))
        kept = contact_search.detect(system, state, reach, skin=True)
        full = contact_search.detect(system, state, reach, skin=False)
        assert kept.same_as(full), f"step {state.step}: the skin found other contacts"
        sim.step()
        if sim.state.time >= model.controls.duration - 1e-12:
            break
    return sim.state.workspace["skin"]


@pytest.mark.parametrize(("name", "build", "steps"), [
    ("rock mass 134 blocks", lambda: _rock_mass(2.5), 40),
    ("pile of 100", lambda: _pile(100), 400),
])
def test_skin_finds_what_full_detection_finds(name: str, build, steps: int) -> None:
    skin = _compare_steps(build(), steps)
    assert skin.refreshes >= 1 and skin.reuses >= 1, (name, skin.refreshes, skin.reuses)


@pytest.mark.parametrize("name", ["wedge", "block_system", "toppling", "stack",
                                  "benched_slope", "terrain_slope", "pushed_block"])
def test_skin_on_the_examples(name: str) -> None:
    model = CASES[name]()
    model.controls = dataclasses.replace(model.controls,
                                         duration=min(model.controls.duration, 0.1))
    _compare_steps(model, 60)


def test_a_block_past_the_margin_brings_a_full_detection() -> None:
    """Moving one block further than the margin must make the next search a full one."""
    model = _rock_mass(5.0)
    sim = Simulation(model)
    sim.step()
    system, state = sim.system, sim.state
    reach = stepping.reach(system, state, stepping.first_attempt(system, state))
    contact_search.detect(system, state, reach, skin=True)
    skin = state.workspace["skin"]
    before = skin.refreshes
    for _ in range(2):
        contact_search.detect(system, state, reach, skin=True)
    assert skin.refreshes == before and skin.served >= 2  # nothing moved: the lists serve
    moved = dataclasses.replace(state, centroid=state.centroid.copy(), cache={})
    b = int(np.flatnonzero(~system.fixed)[0])
    moved.centroid[b, 2] += 1.5 * skin.margin
    kept = contact_search.detect(system, moved, reach, skin=True)
    assert state.workspace["skin"].refreshes == before + 1
    assert kept.same_as(contact_search.detect(system, moved, reach, skin=False))


def test_the_margin_is_a_fraction_of_the_thinnest_block_and_the_reach() -> None:
    from engine.contact.detection import start_search

    system = Simulation(_rock_mass(5.0)).system
    reach = np.full(system.n, 1e-3)
    search = start_search(system.polys0, reach)
    free = ~system.fixed
    margin = skin_margin(search, system.thickness, free)
    assert 0 < margin <= 1e-3 and margin <= 0.05 * system.thickness[free].min()
