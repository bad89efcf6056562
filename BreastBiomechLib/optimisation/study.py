"""The four-model study of the seed's Tables 2 and 3: every model variant fitted to every
compressed case, the landmark errors (Table 2) and the fitted parameters (Table 3) set against
the hidden truth, and a Markdown report of both.

Output folder (rerunning the same command resumes: finished fits are replayed, an interrupted
one continues)::

    <case>/fitting_mesh.vtu         the case's fitting mesh, made once and shared by its fits
    <case>/<model>-<optimiser>/     one fit (:func:`BreastBiomechLib.optimisation.case.fit_compressed_case`)
                   study_row.json   its row of the tables, written when it ends
    study.json                      the settings and every fit's row, rewritten after each fit
    failures.log                    the tasks that failed, with their errors and tracebacks

The fits run as tasks on Dask (:mod:`BreastBiomechLib.cohort`): a local cluster with a
worker per GPU by default, or an existing cluster. A fit whose row shows its budget spent (or
converged) is not run again; a worker lost mid-fit costs only that fit's batch in flight.

Units: landmark errors and displacements in mm (LPS), moduli in Pa.
"""

from __future__ import annotations

import datetime
import json
import platform
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from BreastBiomechLib.cohort import Task, write_json_atomically
from BreastBiomechLib.errors import InputError, reading
from BreastBiomechLib.io.atomic import write_text_atomically
from BreastBiomechLib.io.claims import claimed
from BreastBiomechLib.io.markups import read_markups
from BreastBiomechLib.optimisation.case import FitSettings, fit_compressed_case
from BreastBiomechLib.optimisation.search import OPTIMISERS
from BreastBiomechLib.optimisation.space import HOMOGENEOUS, MODELS, REFERENCE_E

# Forward solves per fit: about 20 per free parameter for the homogeneous variants (1-2 free),
# more for the heterogeneous ones, whose 5-11 parameters interact.
DEFAULT_BUDGETS = {"iso-homo": 24, "aniso-homo": 48, "iso-hetero": 160, "aniso-hetero": 240}
VOXEL_DIAGONAL_MM = float(np.sqrt(1.0 + 1.0 + 2.5**2))  # the seed's 1 x 1 x 2.5 mm voxel: 2.87 mm


@dataclass
class StudySettings:
    """What the study fits: the ``models``, each with the ``optimisers`` and its ``budgets``
    (forward solves; a model missing there gets :data:`DEFAULT_BUDGETS`), and the settings
    shared by every fit (:class:`~BreastBiomechLib.optimisation.case.FitSettings`)."""

    models: tuple[str, ...] = MODELS
    optimisers: tuple[str, ...] = ("cmaes",)
    budgets: dict[str, int] = field(default_factory=lambda: dict(DEFAULT_BUDGETS))
    fibre: tuple[float, float, float] = (0.0, 0.0, 1.0)
    edge_mm: float = 4.0
    seed: int = 0
    objective: str = "nmi"
    bins: int = 64
    tolerance_mm: float = 0.01

    def __post_init__(self) -> None:
        unknown = [m for m in self.models if m not in MODELS]
        if unknown or not self.models:
            raise ValueError(f"choose models among {MODELS}, not {list(self.models)}")
        unknown = [o for o in self.optimisers if o not in OPTIMISERS]
        if unknown or not self.optimisers:
            raise ValueError(f"choose optimisers among {OPTIMISERS}, not {list(self.optimisers)}")
        for model in self.models:
            if self.budget(model) < 1:
                raise ValueError(f"the budget of {model} must be at least one forward solve")

    def budget(self, model: str) -> int:
        return int(self.budgets.get(model, DEFAULT_BUDGETS[model]))

    def fit_settings(self, model: str, optimiser: str) -> FitSettings:
        return FitSettings(model=model, fibre=self.fibre, edge_mm=self.edge_mm, optimiser=optimiser,
                           budget=self.budget(model), seed=self.seed, objective=self.objective, bins=self.bins,
                           tolerance_mm=self.tolerance_mm)


@dataclass
class StudyFit:
    """One fit of the study: ``case`` (folder name), ``model``, ``optimiser``; the best
    ``nmi`` and ``objective``; ``evaluations`` (forward solves), ``failed`` solves, ``seconds``
    (wall time of the runs that made it; a run killed before the fit ended is not counted),
    ``stopped``; the
    ``landmark_errors`` summary (mm); the fitted ``materials`` and the case's ``truth``
    materials ({name: {"E", "nu", "eta"} in Pa}); ``in_family``: whether the truth lies in the
    fitted model family; ``device``: the name of the warp device that solved it (empty in rows
    written before devices were recorded)."""

    case: str
    model: str
    optimiser: str
    nmi: float
    objective: float
    evaluations: int
    failed: int
    seconds: float
    stopped: str
    landmark_errors: dict | None
    materials: dict
    truth: dict
    in_family: bool
    device: str = ""

    def to_dict(self) -> dict:
        return asdict(self)


def truth_in_family(truth: dict, model: str, fibre) -> bool:
    """Whether the truth materials ({tissue: {"E", "nu", optional "eta" and "fibre"}}) are a
    member of the ``model`` family with fat's E as the reference: isotropic variants need no
    eta anywhere; anisotropic ones a fibre along ``fibre`` wherever there is an eta (an
    isotropic tissue is the family's eta at its lower bound, 1 Pa, which is negligible);
    homogeneous ones one material for every tissue."""
    if not np.isclose(truth.get("fat", {}).get("E", REFERENCE_E), REFERENCE_E):
        return False
    anisotropic = model.startswith("aniso")
    for values in truth.values():
        if values.get("eta", 0.0) > 0:
            if not anisotropic or not np.allclose(np.abs(np.asarray(values.get("fibre", fibre), float)),
                                                  np.abs(np.asarray(fibre, float))):
                return False
    if model.endswith("homo"):
        keys = {(v["E"], v["nu"], v.get("eta", 0.0)) for v in truth.values()}
        return len(keys) == 1
    return True


@dataclass
class StudyRun:
    """What a study run leaves: every fit's ``rows`` (also those of earlier runs into the
    folder), the tasks of this run that ``failed`` (:class:`~BreastBiomechLib.cohort.TaskOutcome`,
    with their errors; their tracebacks are in the folder's failures.log) and the ``outcomes`` of
    all its tasks (where and when each ran)."""

    rows: list[StudyFit]
    failed: list
    outcomes: list = field(default_factory=list)


def _fit_done(folder: Path, budget: int) -> bool:
    row = _read_row(folder)
    return row is not None and (row.evaluations >= budget or row.stopped == "converged")


MESH_PRIORITY = 1_000_000  # meshes first: each one lets its case's fits start on any worker


def fit_priority(model: str, budget: int) -> int:
    """A fit's task priority: the larger the budget, the earlier; at equal budgets heterogeneous
    models (more parameters, slower solves) before homogeneous ones. Long fits first keep a
    cluster's workers busy to the end of a study (longest-first scheduling)."""
    return 2 * budget + (0 if model.endswith("homo") else 1)


def study_tasks(case_dirs, out_dir: str | Path, settings: StudySettings) -> list:
    """The study's tasks (:class:`~BreastBiomechLib.cohort.Task`) not yet done in ``out_dir``: a
    fitting mesh per case, then every (model, optimiser) fit of the case, which needs it."""
    cases = [Path(c) for c in case_dirs]
    if not cases:
        raise ValueError("give at least one compressed case folder (`breastbiomech phantom --case N --compressed`)")
    names = [c.name for c in cases]
    if len(set(names)) != len(names):
        raise ValueError(f"the case folders' names must differ (they name the result folders): {names}")
    out = Path(out_dir)
    tasks = []
    for case in cases:
        mesh_file = out / case.name / "fitting_mesh.vtu"
        if not mesh_file.is_file():
            tasks.append(Task(f"mesh/{case.name}", make_fitting_mesh, {"case_dir": str(case), "mesh_file": str(mesh_file),
                                                                       "edge_mm": settings.edge_mm},
                              label=f"{case.name} fitting mesh", priority=MESH_PRIORITY))
        for model in settings.models:
            for optimiser in settings.optimisers:
                folder = out / case.name / f"{model}-{optimiser}"
                if _fit_done(folder, settings.budget(model)):
                    continue
                tasks.append(Task(f"fit/{case.name}/{model}-{optimiser}", fit_study_case,
                                  {"case_dir": str(case), "folder": str(folder), "mesh_file": str(mesh_file),
                                   "settings": settings, "model": model, "optimiser": optimiser},
                                  needs=(f"mesh/{case.name}",), label=f"{case.name} {model} {optimiser}",
                                  priority=fit_priority(model, settings.budget(model))))
    return tasks


def make_fitting_mesh(case_dir: str, mesh_file: str, edge_mm: float, device=None, progress=None) -> dict:
    """A study task: the fitting mesh of the case's labels at ``edge_mm`` (nipple-aware), written
    to ``mesh_file`` (atomically). Returns its size. A phantom case's labels are its ground truth:
    the study meshes them on purpose, to compare the model families (the seed's Table 2) without
    the segmentation's error; a fit meant to be realistic meshes a segmentation (``optimise
    --labels``, the demo, the discrepancy suite)."""
    from BreastBiomechLib.io.images import read_label_map
    from BreastBiomechLib.io.meshes import write_vtu
    from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels

    case, target = Path(case_dir), Path(mesh_file)
    reference = read_markups(case / "landmarks.mrk.json")
    nipple = reference.position("nipple") if "nipple" in reference.labels else None
    mesh = mesh_labels(read_label_map(case / "labels.nrrd"), MeshSettings(edge_mm=edge_mm), nipple_mm=nipple).mesh
    write_vtu(target, mesh)
    return {"nodes": len(mesh.nodes), "tets": len(mesh.tets)}


def fit_study_case(case_dir: str, folder: str, mesh_file: str, settings: StudySettings, model: str, optimiser: str,
                   device=None, progress=None) -> dict:
    """A study task: fit ``model`` with ``optimiser`` to the compressed case on its fitting mesh
    (resuming a fit interrupted in ``folder``) and write its row (:data:`ROW_FILE`, atomically).
    ``progress(message)`` returning False stops the fit after its batch (the row then says
    "cancelled" and a rerun continues). Returns the row."""
    from BreastBiomechLib.phantom.truth_files import read_truth  # scoring only: the truth columns

    case, folder = Path(case_dir), Path(folder)
    earlier = _read_row(folder)
    def report(done, budget, best, phase):
        return None if progress is None else progress(f"{done}/{budget} solves, best {best:.4f}")

    fit = fit_compressed_case(case, folder, settings.fit_settings(model, optimiser), mesh_path=mesh_file,
                              resume=(folder / "evaluations.jsonl").exists(), device=device, progress=report)
    summary = fit.result.summary()
    # scoring only, after the fit has answered: the truth columns of the report's tables
    truth = read_truth(case)["truth"]["materials"]
    row = StudyFit(case.name, model, optimiser, fit.result.best.nmi, fit.result.best.objective,
                   summary["evaluations"], summary["failed"], (earlier.seconds if earlier else 0.0) + summary["seconds"],
                   summary["stopped"], fit.landmark_errors, fit.result.materials, truth,
                   truth_in_family(truth, model, settings.fibre), device_name(device))
    write_json_atomically(folder / ROW_FILE, row.to_dict())
    return row.to_dict()


def run_study(case_dirs, out_dir: str | Path, settings: StudySettings | None = None, device=None,
              placement=None, progress=None) -> StudyRun:
    """Fit every model of ``settings`` with every optimiser to every compressed case in
    ``case_dirs`` (phantom case folders with their ``compressed/`` part); results in
    ``out_dir`` (see the module notes; an existing folder is resumed: done fits are skipped,
    interrupted ones continue). The tasks (:func:`study_tasks`) run at ``placement``
    (:func:`BreastBiomechLib.cohort.place`; None: a local cluster for ``device``);
    ``progress(CohortProgress)`` returning False cancels (raises
    :class:`~BreastBiomechLib.cohort.CohortCancelled`; what finished is kept). study.json is
    rewritten as each fit ends; failed tasks are listed in failures.log with their tracebacks
    and do not stop the others."""
    from BreastBiomechLib.cohort import place, run_tasks, write_json_atomically

    settings = settings or StudySettings()
    out = Path(out_dir)
    tasks = study_tasks(case_dirs, out, settings)
    with claimed(out, "a study"):
        out.mkdir(parents=True, exist_ok=True)
        placement = placement or place(device=device)

        def summarise() -> None:
            write_json_atomically(out / "study.json", {"settings": asdict(settings),
                                                       "fits": [r.to_dict() for r in read_study(out)]})

        def ended(outcome) -> None:
            log_failure(out / "failures.log", outcome)
            summarise()

        outcomes = run_tasks(tasks, placement, progress=progress, on_outcome=ended)
        summarise()
        return StudyRun(read_study(out), [o for o in outcomes if not o.ok], outcomes)


def log_failure(path: Path, outcome) -> None:
    """Append to the log file ``path`` a task's tries that failed: the errors and tracebacks of
    those run again (``earlier_errors``) and, where it failed, its own. Nothing for a task that
    went through at its first try."""
    if outcome.ok and not outcome.earlier_errors:
        return
    now = datetime.datetime.now().isoformat(timespec="seconds")
    with open(path, "a") as stream:
        for n, earlier in enumerate(outcome.earlier_errors, 1):
            stream.write(f"--- {now} {outcome.key}: try {n} of {len(outcome.earlier_errors) + 1}, run again after: "
                         f"{earlier}\n")
        if not outcome.ok:
            stream.write(f"--- {now} {outcome.key}: {outcome.error}\n{outcome.traceback}\n")


ROW_FILE = "study_row.json"


def device_name(device=None) -> str:
    """The name of warp's ``device`` (default: warp's default device), e.g. "NVIDIA H100 80GB HBM3"."""
    import warp as wp

    wp.init()
    return (wp.get_device(device) if device is not None else wp.get_device()).name


def _read_row(folder: Path) -> StudyFit | None:
    """The row (:data:`ROW_FILE`) of the fit in ``folder``, None where there is none yet; a file
    that is not a row raises InputError naming it."""
    path = folder / ROW_FILE
    if not path.is_file():
        return None
    with reading(path, "study row", "remove that fit's folder and run the study again to refit it"):
        row = StudyFit(**json.loads(path.read_text()))
        if not (isinstance(row.nmi, (int, float)) and isinstance(row.objective, (int, float))
                and isinstance(row.materials, dict) and isinstance(row.truth, dict)):
            raise InputError(f"{path}: its nmi, objective, materials or truth is of the wrong kind; remove that "
                             "fit's folder and run the study again to refit it")
    return row


def read_study(out_dir: str | Path) -> list[StudyFit]:
    """Every fit's row in a study folder (none when there is none)."""
    return [_read_row(path.parent) for path in sorted(Path(out_dir).glob(f"*/*/{ROW_FILE}"))]


def best_fits(rows: list[StudyFit]) -> dict[tuple[str, str], StudyFit]:
    """For each (case, model) the fit of the optimiser that reached the lowest objective."""
    best: dict[tuple[str, str], StudyFit] = {}
    for row in rows:
        key = (row.case, row.model)
        if key not in best or row.objective < best[key].objective:
            best[key] = row
    return best


def recovery(row: StudyFit) -> dict[str, dict[str, float]]:
    """For a heterogeneous fit, each tissue's fitted against truth E (relative error) and nu
    (absolute error): {tissue: {"E_rel": ..., "nu_abs": ...}}; fat's E is the reference and left out."""
    if row.model.endswith("homo"):
        return {}
    errors = {}
    for tissue, fitted in row.materials.items():
        truth = row.truth.get(tissue)
        if truth is None:
            continue
        entry = {"nu_abs": abs(fitted["nu"] - truth["nu"])}
        if tissue != "fat":
            entry["E_rel"] = abs(fitted["E"] / truth["E"] - 1.0)
        errors[tissue] = entry
    return errors


def _value(fitted: dict, truth: dict | None, key: str, scale: float, form: str) -> str:
    """A fitted value / ``scale`` with the truth's in brackets (a truth without ``key`` has 0)."""
    text = format(fitted[key] / scale, form)
    return text + (f" [{format(truth.get(key, 0.0) / scale, form)}]" if truth else "")


def _mean_sd(summary: dict | None, key: str, with_max: bool = False) -> str:
    if not summary:
        return "-"
    s = summary[key]
    return f"{s['mean']:.2f} ± {s['sd']:.2f}" + (f" ({s['max']:.1f})" if with_max else "")


def _devices(rows: list[StudyFit]) -> str:
    """Which devices solved the fits ("Solved on: NAME (n fits); ..."), or nothing when no row says."""
    counts = Counter(row.device or "device not recorded" for row in rows)
    if set(counts) == {"device not recorded"}:
        return ""
    return "Solved on: " + "; ".join(f"{name} ({n} fit{'s' * (n != 1)})" for name, n in counts.items()) + ". "


def study_markdown(rows: list[StudyFit], settings: StudySettings, provenance: dict) -> str:
    """The study as Markdown: the settings and ``provenance`` ({"date", "command", ...}), the devices
    that solved the fits,
    landmark errors as the seed's Table 2, fitted against truth parameters as its Table 3, the
    recovery where the truth lies in the fitted family, and the optimisers side by side."""
    best = best_fits(rows)
    cases = sorted({r.case for r in rows}, key=_natural)
    models = [m for m in ("aniso-hetero", "aniso-homo", "iso-hetero", "iso-homo") if any(k[1] == m for k in best)]
    optimisers = [o for o in OPTIMISERS if any(r.optimiser == o for r in rows)]  # also other runs' fits
    lines = ["| " + " | ".join(f"{k}: {v}" for k, v in provenance.items()) + " |",
             "|" + "---|" * len(provenance), "",
             f"Fits: {', '.join(optimisers)}; budgets (forward solves) "
             + ", ".join(f"{m} {settings.budget(m)}" for m in models)
             + f"; fitting mesh {settings.edge_mm:g} mm; objective {settings.objective} ({settings.bins} bins); "
             f"fibre (LPS) {list(settings.fibre)}; seed {settings.seed}. " + _devices(rows)
             + "Where several optimisers fitted a model, the tables show the one that reached the lower objective.", "",
             "### Landmark errors (the seed's Table 2)", "",
             "Mean ± sd (max) over the 17 landmarks, mm; * marks fits whose truth lies in the fitted family.", "",
             "| case | landmark displacement | " + " | ".join(models) + " |",
             "|---|---|" + "---|" * len(models)]
    for case in cases:
        first = next((best[(case, m)] for m in models if (case, m) in best), None)
        cells = []
        for m in models:
            row = best.get((case, m))
            cells.append("-" if row is None else _mean_sd(row.landmark_errors, "error_mm", True)
                         + ("*" if row.in_family else ""))
        lines.append(f"| {case} | {_mean_sd(first.landmark_errors if first else None, 'displacement_mm', True)} | "
                     + " | ".join(cells) + " |")
    lines += ["", "### Fitted parameters (the seed's Table 3)", "",
              "E in kPa, eta in kPa; truth in brackets. Fat's E is the reference (10 kPa).", ""]
    for model in [m for m in models if not m.endswith("homo")] + [m for m in models if m.endswith("homo")]:
        lines += [f"**{model}**", "", "| case | material | E | nu | eta | NMI | solves (failed) | wall time (s) |",
                  "|---|---|---|---|---|---|---|---|"]
        for case in cases:
            row = best.get((case, model))
            if row is None:
                continue
            for i, (name, fitted) in enumerate(row.materials.items()):
                truth = row.truth.get(name) if name != HOMOGENEOUS else None
                extra = f"{row.nmi:.4f} | {row.evaluations} ({row.failed}) | {row.seconds:.0f}" if i == 0 else " |  | "
                eta = _value(fitted, truth, "eta", 1e3, ".4g") if model.startswith("aniso") else "-"
                lines.append(f"| {case if i == 0 else ''} | {name} | {_value(fitted, truth, 'E', 1e3, '.4g')} | "
                             f"{_value(fitted, truth, 'nu', 1.0, '.4f')} | {eta} | {extra} |")
        lines.append("")
    family = [r for r in best.values() if r.in_family and not r.model.endswith("homo")]
    if family:
        lines += ["### Recovery where the truth lies in the fitted family", "",
                  "| case | model | largest E error (tissue) | largest nu error | landmark error mean (max), mm | "
                  f"below one voxel diagonal ({VOXEL_DIAGONAL_MM:.2f} mm) |", "|---|---|---|---|---|---|"]
        for row in sorted(family, key=lambda r: (_natural(r.case), r.model)):
            errors = recovery(row)
            e_tissue, e_worst = max(((t, v["E_rel"]) for t, v in errors.items() if "E_rel" in v),
                                    key=lambda item: item[1], default=("-", float("nan")))
            nu_worst = max((v["nu_abs"] for v in errors.values()), default=float("nan"))
            s = row.landmark_errors["error_mm"] if row.landmark_errors else None
            lines.append(f"| {row.case} | {row.model} | {e_worst:.1%} ({e_tissue}) | {nu_worst:.4f} | "
                         + (f"{s['mean']:.2f} ({s['max']:.2f}) | {'yes' if s['mean'] < VOXEL_DIAGONAL_MM else 'no'} |"
                            if s else "- | - |"))
        lines.append("")
    if len({r.optimiser for r in rows}) > 1:
        lines += ["### Optimisers on the same fits", "",
                  "| case | model | optimiser | best NMI | solves (failed) | wall time (s) | stopped |",
                  "|---|---|---|---|---|---|---|"]
        for row in sorted(rows, key=lambda r: (_natural(r.case), r.model, r.optimiser)):
            if sum(1 for r in rows if (r.case, r.model) == (row.case, row.model)) > 1:
                lines.append(f"| {row.case} | {row.model} | {row.optimiser} | {row.nmi:.4f} | {row.evaluations} "
                             f"({row.failed}) | {row.seconds:.0f} | {row.stopped} |")
        lines.append("")
    return "\n".join(lines)


MARKERS = ("<!-- study tables: begin (written by `breastbiomech study --report`) -->",
           "<!-- study tables: end -->")


def write_report(path: str | Path, tables: str) -> Path:
    """Put ``tables`` between the :data:`MARKERS` of the Markdown file ``path``, keeping the prose
    around them; a new file, or one without the markers, gets them appended."""
    path = Path(path)
    text = path.read_text() if path.is_file() else ""
    begin, end = MARKERS
    if begin in text and end in text and text.index(begin) < text.index(end):
        before, rest = text.split(begin, 1)
        after = rest.split(end, 1)[1]
    else:
        before, after = (text.rstrip() + "\n\n" if text.strip() else ""), "\n"
    write_text_atomically(path, f"{before}{begin}\n{tables.strip()}\n{end}{after}")
    return path


def provenance(device: str, command: str, date: str) -> dict:
    """The provenance row of a study report: date, the device the report was written on (each
    fit's own device is in its row), command, and the software."""
    import warp as wp

    return {"date": date, "report written on": device, "command": f"`{command}`", "python": platform.python_version(),
            "warp": wp.config.version}


def _natural(name: str):
    digits = "".join(ch for ch in name if ch.isdigit())
    return (name.rstrip("0123456789"), int(digits) if digits else -1, name)

