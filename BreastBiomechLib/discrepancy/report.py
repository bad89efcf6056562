"""The diagnosis report: Markdown with the verdict of each round, the ranked candidates with
their statistics, the residual by region, and before/after figures of each added effect."""

from __future__ import annotations

from pathlib import Path

from BreastBiomechLib.discrepancy.design_record import not_designed, read_design
from BreastBiomechLib.discrepancy.diagnosis import closest_rivals, inseparable_sentence
from BreastBiomechLib.discrepancy.verdicts import overall_phrase
from BreastBiomechLib.io.atomic import write_text_atomically


def _number(value, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        if value != value:
            return "-"
        return f"{value:.{digits}g}"
    return str(value)


def _absorbed(candidate: dict) -> str:
    """The share of a candidate's signature the fitted parameters reproduce, and the one that
    reproduces most of it ("-" in a record made before it was computed)."""
    share = candidate.get("absorbed")
    if share is None or share != share:
        return "-"
    by = candidate.get("absorbed_by") or {}
    return f"{share:.0%}" + (f" ({by['name']} {by['correlation']:.2f})" if by else "")


def _detectable(candidate: dict) -> str:
    """The smallest sizes of a candidate's parameters its test would see ("-" in a record made
    before they were computed; "none" where the fit takes the effect up whole)."""
    sizes = candidate.get("detectable")
    if not sizes:
        return "-"
    return ", ".join("none" if v is None else _number(v, 2) for v in sizes)


def _rival(rival: tuple[str, float] | None, titles: dict) -> str:
    return "-" if rival is None else f"{titles.get(rival[0], rival[0])} {rival[1]:.2f}"


def _candidates_table(candidates: list[dict], correlations: dict | None = None) -> str:
    rivals = closest_rivals(candidates, correlations or {})
    rows = ["| rank | effect | score S (dof) | S per dof | by channel | linearised dBIC | p (corrected) | "
            "could explain | localisation | absorbed by the fit | closest rival | smallest size seen | refit | dBIC | "
            "residual removed | change where it acts (mm) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    titles = {c["name"]: c["title"] for c in candidates}
    rank = 0
    for c in candidates:
        if c["skipped"]:
            continue
        rank += 1
        refit = c.get("refit") or {}
        channels = "; ".join(f"{name} {t['statistic']:.1f} ({t['dof']}), p {t['p_value']:.2g}"
                             for name, t in (c.get("channels") or {}).items()) or "-"
        per_dof = _number(c["statistic"] / c["dof"], 3) if c["dof"] else "-"
        rows.append(f"| {rank} | {c['title']} | {c['statistic']:.1f} ({c['dof']}) | {per_dof} | {channels} | "
                    f"{_number(c.get('linear_delta_bic'), 3)} | {_number(c['p_adjusted'], 2)} | "
                    f"{c['explained_fraction']:.0%} | {c['localisation']:.0%} | {_absorbed(c)} | "
                    f"{_rival(rivals.get(c['name']), titles)} | {_detectable(c)} | "
                    f"{refit.get('described', '-')} | "
                    f"{_number(refit.get('delta_bic'), 3)} | "
                    + (f"{refit['removed']:.0%}" if "removed" in refit else "-") + " | "
                    + _number(refit.get("effect_mm"), 2) + " |")
    skipped = [f"{c['title']} ({c['skipped']})" for c in candidates if c["skipped"]]
    refits = [c["refit"] for c in candidates if (c.get("refit") or {}).get("rss_fitted_only") is not None]
    note = ""
    if refits and refits[0]["rss_before"] > 0:
        alone = 1.0 - refits[0]["rss_fitted_only"] / refits[0]["rss_before"]
        note = (f"\n\ndBIC and the residual removed are counted against the same refit of the fitted parameters "
                f"alone (the nested model), which removed {max(alone, 0.0):.0%} of the residual by itself.")
    note += ("\n\nCandidates are ranked by their linearised dBIC (-S + dof ln n: a candidate with more parameters "
             "does not win by its degrees of freedom alone); the corrected p is the smallest of the pooled and the "
             "channels' score tests, Bonferroni-corrected over them and over the candidates. *Change where it acts*: "
             "the RMS of the largest tenth of the changes the refit makes to the features, compared with the "
             "model-error floor before an effect is named.")
    note += ("\n\n*Absorbed by the fit*: the share of the candidate's signature that the fitted parameters "
             "reproduce (in brackets the one that alone reproduces most, and its correlation); near 100 % the fit has "
             "taken the effect up and no test of the residual can see it. *Smallest size seen*: the size of each "
             "of the candidate's parameters (its units, from its off value, along its secant) at which its score "
             "test would reach the verdict's level in four cases of five at this case's noise; beyond the "
             "parameter's range the case could not have shown the effect at all. *Closest rival*: the tested "
             "candidate whose signature correlates most with this one's once the fitted parameters are accounted "
             "for (the largest canonical correlation).")
    if correlations is not None:
        note += "\n\n" + inseparable_sentence(candidates, correlations)
    return "\n".join(rows) + note + ("\n\nNot tested: " + "; ".join(skipped) + "." if skipped else "")


def _regions_table(before: dict, after: dict | None) -> str:
    rows = ["| region | channel | features | RMS residual before (mm) | after (mm) | mean z² before |",
            "|---|---|---|---|---|---|"]
    for region, channels in before["regions"].items():
        for channel, figures in channels.items():
            later = (after or {}).get("regions", {}).get(region, {}).get(channel)
            rows.append(f"| {region} | {channel} | {figures['features']} | {figures['rms_mm']:.2f} | "
                        f"{later['rms_mm']:.2f} |" if later else
                        f"| {region} | {channel} | {figures['features']} | {figures['rms_mm']:.2f} | - |")
            rows[-1] += f" {figures['mean_square_whitened']:.2f} |"
    return "\n".join(rows)


def _field_section(record: dict) -> list[str]:
    """The residual displacement field of a round: its accuracy, its magnitude by region before
    and after, and the picture."""
    before = record["before"].get("residual_field")
    if not before:
        return []
    after = (record.get("after") or {}).get("residual_field")
    accuracy = before["accuracy"]
    lines = ["### Residual displacement field", "",
             "From a deformable registration (demons) of the model's predicted image to the measured one: "
             f"mean |r| {before['mean_mm']:.2f} mm (95th percentile {before['p95_mm']:.2f} mm)"
             + (f", after the refit {after['mean_mm']:.2f} mm ({after['p95_mm']:.2f} mm)" if after else "") + "."]
    said = []
    if "known_rms_error_mm" in accuracy:
        said.append(f"it recovers a known smooth displacement of {accuracy['known_rms_mm']:.2f} mm RMS to "
                    f"{accuracy['known_rms_error_mm']:.2f} mm RMS")
    if "landmark_rms_difference_mm" in accuracy:
        said.append(f"at the {accuracy['landmarks']} landmarks it differs from their marked residuals "
                    f"({accuracy['landmark_rms_residual_mm']:.2f} mm RMS) by {accuracy['landmark_rms_difference_mm']:.2f} "
                    "mm RMS")
    if said:
        lines[-1] += " Its accuracy: " + "; ".join(said) + ". Sliding along a featureless surface (a plate's contact) " \
                     "is invisible to it; it is evidence for where, not a test statistic."
    rows = ["| region | nodes | mean residual before (mm) | after (mm) |", "|---|---|---|---|"]
    for region, figures in before["regions"].items():
        later = (after or {}).get("regions", {}).get(region)
        rows.append(f"| {region} | {figures['nodes']} | {figures['mean_mm']:.2f} | "
                    + (f"{later['mean_mm']:.2f} |" if later else "- |"))
    lines += ["", "\n".join(rows)]
    if record.get("residual_picture"):
        lines += ["", f"![residual displacement field, round {record['round']}]({record['residual_picture']})"]
    return lines + [""]


def _floor_phrase(record: dict) -> str:
    """The model-error floor a round used: measured (its RMS, the estimate's largest group, the
    meshes) or fixed."""
    floor = record.get("floor") or {}
    if "rms_mm" not in floor:
        fixed = floor.get("fixed_mm", record["noise"]["model_sd_mm"])
        if floor.get("not_measured"):
            return f"model-error floor {fixed:g} mm (fixed: measuring it from the case failed: {floor['not_measured']})"
        return f"model-error floor {fixed:g} mm (fixed)"
    largest = floor["largest"]
    return (f"model-error floor measured from the case: {floor['rms_mm']:.2f} mm RMS over the features (at least "
            f"{floor['lower_bound_mm']:g} mm; the fitting mesh's discretisation error, estimated against its "
            f"refinement of {floor['tets'][1]} tets, {floor['discretisation_rms_mm']:.2f} mm RMS, largest in "
            f"{largest['group']} at {largest['rms_mm']:.2f} mm)")


def _measures_line(name: str, m: dict) -> str:
    landmark = m.get("landmark_error_mm")
    text = f"{name}: NMI {m['nmi']:.4f}, RMS feature residual {m['residual_rms_mm']:.2f} mm"
    if landmark:
        text += f", landmark error {landmark['mean']:.2f} mm mean (max {landmark['max']:.2f})"
    for state, figures in (m.get("states") or {}).items():  # a joint fit's further measured states
        text += f"; state {state}: NMI {figures['nmi']:.4f}"
        if figures.get("landmark_error_mm"):
            text += f", landmark error {figures['landmark_error_mm']['mean']:.2f} mm mean"
    return text


def _features_phrase(features: dict) -> str:
    """How many features a round compared, by channel, and by measured state where it stacked several."""
    text = (f"{features['count']} features "
            f"({', '.join(f'{k} {v}' for k, v in features['channels'].items())})")
    states = features.get("states") or {}
    if len(states) > 1:
        text += f" in {len(states)} measured states stacked ({', '.join(f'{k} {v}' for k, v in states.items())})"
    return text


def design_section(run) -> list[str]:
    """The next measurement: the design made after the last round (design.json beside the
    report), or where to make it; nothing while the last round waits for a decision."""
    from BreastBiomechLib.discrepancy.session import is_open

    last = run.rounds[-1]
    if is_open(last):
        return []
    record = read_design(run.folder, last["round"])
    if record is None:
        return ["## The next measurement", "",
                "Not designed after this round: `breastbiomech diagnose ... --resume --design` (or `breastbiomech "
                "design CASE --fit FIT --diagnosis DIR --out NEW`) simulates further acquisitions from the model and "
                "says which would tell apart the candidates this round could not.", ""]
    if not record["designed_for"]:
        return ["## The next measurement", "", f"After round {last['round']}: {not_designed(record)}", ""]
    from BreastBiomechLib.discrepancy.design import Design

    return [Design.from_dict(record).markdown()]


def write_report(run, path: Path, pictures: list[tuple[str, str]] = ()) -> Path:
    """Write the Markdown report of ``run`` (a :class:`~BreastBiomechLib.discrepancy.workflow.DiagnosisRun`)
    with ``pictures`` ((caption, file name beside the report) each, e.g. Slicer's slice views) at its end."""
    parts = ["# Model-discrepancy diagnosis", "",
             f"**Final verdict: {run.final['sentence']}**", ""]
    if run.added:
        parts += [f"Effects added: {', '.join(run.added)}.", ""]
    for record in run.rounds:
        d = record["diagnosis"]
        o = d["overall"]
        noise = record["noise"]
        parts += [f"## Round {record['round']}: {d['verdict']}", "", d["sentence"], "",
                  f"{_features_phrase(record['features'])}; "
                  f"noise: landmarks {noise['landmark_sd_mm']:g} mm, {_floor_phrase(record)}. "
                  f"Overall test ({overall_phrase(o)}; T/dof of all features {o['per_dof']:.2f}); "
                  f"{d['solves']} forward solves; {record['seconds']:.0f} s.", "",
                  "### Candidates", "", _candidates_table(d["candidates"], d.get("correlations")), "",
                  "### Residual by region", "", _regions_table(record["before"], record.get("after")), "",
                  *_field_section(record),
                  _measures_line("Before", record["before"])]
        if record.get("after"):
            parts += ["", _measures_line(f"After adding {record['added']}", record["after"])]
        parts += [""]
    parts += design_section(run)
    if pictures:
        parts += ["## Views", ""] + [f"![{caption}]({name})\n" for caption, name in pictures]
    return write_text_atomically(path, "\n".join(parts) + "\n")
