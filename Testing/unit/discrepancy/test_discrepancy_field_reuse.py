"""A round's model after its refit is the next round's model before it: its residual field (a
deformable registration, seconds to minutes) is made once, not again for the same model."""

from types import SimpleNamespace

import numpy as np

from BreastBiomechLib.discrepancy import registration
from BreastBiomechLib.discrepancy.session import SAME_SOLUTION_MM, FieldRecorder


def test_the_same_models_field_is_made_once(monkeypatch):
    made = []

    def register(fitted, displacement, body, settings):
        made.append(displacement.copy())
        return object()

    monkeypatch.setattr(registration, "residual_field_of", register)
    recorder = FieldRecorder(SimpleNamespace(first=lambda u: u[:4]), settings=None, node_regions=None, body=None)
    u = np.random.default_rng(0).normal(0.0, 3.0, (6, 3))
    first = recorder.field(u)
    again = recorder.field(u + 0.5 * SAME_SOLUTION_MM)  # re-solved: the same model
    assert again is first and len(made) == 1
    other = recorder.field(u + 3 * SAME_SOLUTION_MM)  # another model
    assert other is not first and len(made) == 2
    changed_elsewhere = u.copy()
    changed_elsewhere[5] += 1.0  # only outside the first state: the same field
    assert recorder.field(changed_elsewhere + 3 * SAME_SOLUTION_MM) is other and len(made) == 2
