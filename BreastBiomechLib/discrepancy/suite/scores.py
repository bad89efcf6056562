"""Scoring the hidden-effect suite: each case's answer against the effect its truth hides, and
the suite's figures (confusion matrix, right verdicts, false alarms, how far an added effect
closes the gap).

A case's **answer** is what the first round says: the named effect, "ambiguous", "unexplained" or
"none". A case is **right** when: null - nothing significant; one or two library effects - the
rounds add exactly those effects; an effect outside the library - "unexplained discrepancy" with
nothing added. Where effects were added, the landmark error's fall is 1 - after / before (mean
over the landmarks, mm; against the truth's exact landmarks where the suite gives them, as the
measured ones carry a localisation error) and the NMI gap closed is (after - before) / (truth -
before), "truth" the NMI of the image the truth parameters predict (the ceiling of any model).
"""

from __future__ import annotations

import numpy as np

from BreastBiomechLib.discrepancy.suite.cases import HIDDEN_EFFECTS, MISSING, NONE, UNEXPLAINED, SuiteCase

TARGETS = {"right_verdicts": 0.9, "false_alarms": 0.1, "landmark_error_fall": 0.5, "nmi_gap_closed": 0.5,
           "h100_seconds_per_case": 300.0}


def answer(diagnosis: dict) -> str:
    """A round's answer in one word: the named effect, "ambiguous", "unexplained" or "none"."""
    verdict = diagnosis["verdict"]
    if verdict == MISSING:
        return diagnosis["effect"]
    return {NONE: "none", UNEXPLAINED: "unexplained"}.get(verdict, "ambiguous")


def case_result(case: SuiteCase, rounds: list[dict], truth_nmi: float, prepared: dict, seconds: dict,
                true_errors: dict | None = None) -> dict:
    """One case's record: its answers round by round, the effects added, whether it is right,
    the landmark error (mm; ``true_errors`` {"before", "after"}: against the truth's exact
    landmarks, else against the measured ones) and NMI before the first round and after the last
    refit, the truth parameters' NMI, and the anatomy's and the case's figures."""
    true_errors = true_errors or {}
    added = [r["added"] for r in rounds if r.get("added")]
    verdicts = [r["diagnosis"]["verdict"] for r in rounds]
    first = answer(rounds[0]["diagnosis"])
    kind = case.hidden.kind
    if kind == "null":
        correct = first == "none"
    elif kind == "unknown":
        correct = first == "unexplained" and not added
    else:
        correct = sorted(added) == sorted(case.hidden.expected)
    before = rounds[0]["before"]
    last = next((r["after"] for r in reversed(rounds) if r.get("after")), None)
    out = {"case": case.name, "anatomy": case.anatomy, "hidden": case.hidden.name, "kind": kind,
           "expected": list(case.hidden.expected), "right_verdict": case.hidden.right_verdict,
           "answer": first, "verdicts": verdicts, "added": added, "correct": bool(correct),
           "landmark_error_before_mm": true_errors.get("before", before.get("landmark_error_mm", {}).get("mean")),
           "measured_landmark_error_before_mm": before.get("landmark_error_mm", {}).get("mean"),
           "nmi_before": before["nmi"], "nmi_truth": truth_nmi,
           "overall_statistic": rounds[0]["diagnosis"]["overall"]["statistic"],
           "overall_dof": rounds[0]["diagnosis"]["overall"]["dof"],
           "overall_p": rounds[0]["diagnosis"]["overall"]["p_value"],
           "anatomy_figures": prepared, "seconds": {k: round(v, 1) for k, v in seconds.items()}}
    if last is not None:
        out["landmark_error_after_mm"] = true_errors.get("after", last.get("landmark_error_mm", {}).get("mean"))
        out["measured_landmark_error_after_mm"] = last.get("landmark_error_mm", {}).get("mean")
        out["nmi_after"] = last["nmi"]
        if out["landmark_error_before_mm"] and out["landmark_error_after_mm"] is not None:
            out["landmark_error_fall"] = 1.0 - out["landmark_error_after_mm"] / out["landmark_error_before_mm"]
        gap = truth_nmi - before["nmi"]
        out["nmi_gap_closed"] = (last["nmi"] - before["nmi"]) / gap if gap > 0 else None
    return out


def suite_scores(results: list[dict]) -> dict:
    """The suite's figures from its cases' results (failed cases counted apart)."""
    done = [r for r in results if "error" not in r]
    failed = [r for r in results if "error" in r]
    hidden = [r for r in done if r["kind"] != "null"]
    null = [r for r in done if r["kind"] == "null"]
    named = [r for r in done if r["kind"] in ("single", "two") and r["correct"]]
    answers = sorted({r["answer"] for r in done})
    confusion = {}
    for name in HIDDEN_EFFECTS:
        rows = [r for r in done if r["hidden"] == name]
        if rows:
            confusion[name] = {a: sum(r["answer"] == a for r in rows) for a in answers}

    def mean(key, rows):
        values = [r[key] for r in rows if r.get(key) is not None]
        return float(np.mean(values)) if values else None

    return {
        "cases": len(results), "finished": len(done), "failed": [{"case": r["case"], "error": r["error"]} for r in failed],
        "right_verdicts": mean("correct", hidden) if hidden else None, "hidden_cases": len(hidden),
        "false_alarms": float(np.mean([not r["correct"] for r in null])) if null else None, "null_cases": len(null),
        "right_by_kind": {kind: [sum(r["correct"] for r in done if r["kind"] == kind),
                                 sum(r["kind"] == kind for r in done)] for kind in ("null", "single", "two", "unknown")},
        "landmark_error_fall": mean("landmark_error_fall", named), "nmi_gap_closed": mean("nmi_gap_closed", named),
        "landmark_error_before_mm": mean("landmark_error_before_mm", named),
        "landmark_error_after_mm": mean("landmark_error_after_mm", named),
        "seconds_per_case": mean("total_seconds", [r | {"total_seconds": sum(r["seconds"].values())} for r in done]),
        "confusion": confusion, "answers": answers, "targets": TARGETS,
    }


def _percent(value) -> str:
    return "–" if value is None else f"{value:.0%}"


def scores_markdown(scores: dict, results: list[dict]) -> str:
    """The scores as Markdown: the headline figures against the issue's targets, the confusion
    matrix (hidden effect x first-round answer) and one row per case."""
    answers = scores["answers"]
    seconds = "–" if scores["seconds_per_case"] is None else f"{scores['seconds_per_case']:.0f}"
    lines = ["| figure | value | target |", "|---|---|---|",
             f"| right verdicts (hidden-effect cases) | {_percent(scores['right_verdicts'])} of "
             f"{scores['hidden_cases']} | ≥ 90 % |",
             f"| false alarms (null cases) | {_percent(scores['false_alarms'])} of {scores['null_cases']} | ≤ 10 % |",
             f"| landmark error fall where the right effect was added | {_percent(scores['landmark_error_fall'])} | ≥ 50 % |",
             f"| NMI gap to the truth-parameter image closed | {_percent(scores['nmi_gap_closed'])} | ≥ 50 % |",
             f"| wall seconds per case (truth, fit, diagnosis) | {seconds} | ≤ 300 on an H100 |",
             "", "| hidden effect | " + " | ".join(answers) + " |", "|---|" + "---|" * len(answers)]
    for name, row in scores["confusion"].items():
        lines.append(f"| {name} | " + " | ".join(str(row.get(a, 0)) for a in answers) + " |")
    lines += ["", "| case | answer | rounds | right | landmark error before → after (mm) | NMI before → after (truth) |",
              "|---|---|---|---|---|---|"]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['case']} | failed: {r['error']} | | | | |")
            continue
        errors = (f"{r['landmark_error_before_mm']:.2f} → {r['landmark_error_after_mm']:.2f}"
                  if r.get("landmark_error_after_mm") is not None else f"{r['landmark_error_before_mm']:.2f}")
        nmi = (f"{r['nmi_before']:.4f} → {r['nmi_after']:.4f}" if r.get("nmi_after") is not None
               else f"{r['nmi_before']:.4f}") + f" ({r['nmi_truth']:.4f})"
        lines.append(f"| {r['case']} | {r['answer']} | {'; '.join(r['verdicts'])} | {'yes' if r['correct'] else 'no'} "
                     f"| {errors} | {nmi} |")
    return "\n".join(lines) + "\n"
