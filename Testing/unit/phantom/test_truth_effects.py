"""The suite's hidden truths are made apart from the discrepancy workflow's candidates (issue 77,
point 5): the truth's plate turned about a pivot of its own (phantom.plate_pose) against the
plate candidate's pose, and no shared implementation of an effect."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

LIBRARY = Path(__file__).resolve().parents[3] / "BreastBiomechLib"


def test_a_truth_plate_turned_about_its_final_point_is_the_candidates_tilt():
    """Two implementations, one pose: turned about its final point the truth's plate is the
    candidate's tilted plate (point, normal, travel); about a pivot b along its second tilt axis,
    turned by theta about its first, its plane is the candidate's tilt with the offset -b sin
    theta - the family the candidate spans with its tilts and offsets together."""
    from BreastBiomechLib.phantom.plate_pose import turned_plate
    from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression
    from BreastBiomechLib.solver.placement import posed_plate

    model = hemi_ellipsoid_compression(10.0)
    nodes = model.mesh.nodes
    for plate in model.loading.plates:
        for tilt in ([1.5, 0.0], [0.0, -2.0], [0.7, 0.9]):
            ours, theirs = turned_plate(plate, nodes, tilt), posed_plate(plate, nodes, tilt)
            np.testing.assert_allclose(ours.normal, theirs.normal, atol=1e-12)
            np.testing.assert_allclose(ours.point, theirs.point, atol=1e-9)
            np.testing.assert_allclose(ours.displacement, theirs.displacement, atol=1e-9)
        theta, b = 2.0, 40.0
        ours = turned_plate(plate, nodes, [theta, 0.0], [0.0, b, 0.0])
        theirs = posed_plate(plate, nodes, [theta, 0.0], offset_mm=-b * np.sin(np.radians(theta)))
        np.testing.assert_allclose(ours.normal, theirs.normal, atol=1e-12)
        ours_final, theirs_final = ours.point + ours.displacement, theirs.point + theirs.displacement
        assert (ours_final - theirs_final) @ ours.normal == pytest.approx(0.0, abs=1e-9)  # one plane
        # and in its plane by b (1 - cos theta), which a flat face does not feel
        assert np.linalg.norm(ours_final - theirs_final) == pytest.approx(b * (1 - np.cos(np.radians(theta))), rel=1e-6)
    with pytest.raises(ValueError, match="two finite angles"):
        turned_plate(model.loading.plates[0], nodes, [1.0], [0.0, 0.0, 0.0])


def test_a_truth_names_its_pivot_and_refuses_one_without_a_tilt():
    from BreastBiomechLib.phantom.compressed import TruthModel

    truth = TruthModel(plate_tilt_deg=[[1.0, 0.0], [0.0, 0.0]], plate_pivot_mm=[[0, 30, -10], [0, 0, 0]])
    assert truth.hidden_effects == ["plate tilt [[1.0, 0.0], [0.0, 0.0]] about [[0.0, 30.0, -10.0], [0.0, 0.0, 0.0]] mm"]
    for bad in ({"plate_pivot_mm": [[0, 0, 0], [0, 0, 0]]}, {"plate_tilt_deg": [[1, 0], [0, 0]], "plate_pivot_mm": [[0, 0]]}):
        with pytest.raises(ValueError, match="plate_pivot_mm"):
            TruthModel(**bad)


def _imports(path: Path) -> set[str]:
    """The modules ``path`` imports (absolute names), at any depth of its code."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            names |= {node.module} | {f"{node.module}.{alias.name}" for alias in node.names}
    return names


def test_the_suite_truths_and_the_candidates_share_no_effect_implementation():
    """The hidden skin and plate pose of a truth and the candidates for them are made by separate
    code: the truth's (phantom.compressed, phantom.skin_elements, phantom.plate_pose) imports
    neither the candidates nor the skin candidate's partial-volume weighting (mesh.skin) nor the
    plate candidate's posing (posed_plate), and the candidates import nothing of the phantom."""
    truth = set().union(*(_imports(LIBRARY / "phantom" / name)
                          for name in ("compressed.py", "skin_elements.py", "plate_pose.py")))
    assert not {n for n in truth if n.startswith(("BreastBiomechLib.mesh.skin", "BreastBiomechLib.discrepancy"))}
    assert "BreastBiomechLib.solver.placement.posed_plate" not in truth
    for path in (LIBRARY / "discrepancy" / "effects").glob("*.py"):
        assert not {n for n in _imports(path) if n.startswith("BreastBiomechLib.phantom")}, path
