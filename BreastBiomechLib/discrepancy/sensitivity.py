"""How the features move with each parameter at the current model: the fitted (nuisance)
parameters by a forward difference, each candidate effect's parameters by a secant from their
off value to a realistic step (:class:`~BreastBiomechLib.discrepancy.effects.EffectParameter`).
Every variant is built first and solved together from rest: one batched launch for all that
change only materials and plates, one per effect that changes the loading (why not from the
current model's equilibrium: :mod:`~BreastBiomechLib.discrepancy.variants`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from BreastBiomechLib.discrepancy.effects import Effect
from BreastBiomechLib.discrepancy.observations import Observations
from BreastBiomechLib.discrepancy.state import FIT_STEP, ModelState
from BreastBiomechLib.discrepancy.variants import Outcome, solve_variants
from BreastBiomechLib.timing import stage, staged

UNSOLVED = "its variant did not solve"  # how a skipped effect whose model failed is said


@dataclass
class Sensitivities:
    """At the current model: its solution ``displacement`` (N, 3) mm and ``features`` (n,);
    ``nuisance`` (n, p) the features' change per unit of each nuisance parameter (keys
    ``nuisance_keys``); ``effects`` {name: (n, k)} per unit of each candidate's parameters;
    ``fields`` {name: (k, N, 3)} the nodal displacement change per unit of each; ``steps``
    {name: (k,)} the secant step each was taken over from its off value (each secant model, the
    current one with that one parameter moved by its step, solved: its displacement is
    ``displacement + fields[name][j] * steps[name][j]``); ``skipped`` {name: reason} the
    candidates that could not be evaluated; ``solves`` how many forward solves it took;
    ``held`` {nuisance key: displacement (N, 3) mm, None where it did not solve} of the current
    model with that parameter held at a value asked for (:func:`sensitivities`' ``held``)."""

    displacement: np.ndarray
    features: np.ndarray
    nuisance_keys: list[str]
    nuisance: np.ndarray
    effects: dict[str, np.ndarray] = field(default_factory=dict)
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    steps: dict[str, np.ndarray] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    solves: int = 0
    held: dict[str, np.ndarray | None] = field(default_factory=dict)


@staged("sensitivities")
def sensitivities(state: ModelState, observations: Observations | Callable[[np.ndarray], Observations],
                  candidates: list[Effect], progress: Callable[[str], None] | None = None,
                  current: Outcome | None = None, held: dict[str, float] | None = None) -> Sensitivities:
    """The :class:`Sensitivities` of ``observations`` at ``state`` for the ``candidates`` (effects
    not yet added, each available for this fit). ``observations``: the measured features, or a
    function of the current model's displacement (N, 3) mm that makes them (a simulated
    acquisition, whose measurement is that solve's prediction: the current model is solved in the
    variants' launch, not before it). A model that inverts an element is solved again
    alone with a slower load (:func:`solve_variants`); a nuisance difference that still fails is
    taken on the other side, an effect's secant to half its step (a candidate still failing is
    skipped with the reason); raises a RuntimeError
    when the current model or a nuisance variant still fails to solve. ``current``: the solve of
    ``state.variant()`` where the caller has it (not solved again; ``solves`` leaves it out).
    ``held`` {nuisance key: value}: the current model with each of those parameters at that value
    (its nuisance coordinate, e.g. a modulus held at its plausible range's end) solved in the same
    launch, returned as :attr:`Sensitivities.held`."""
    fitted = state.fitted
    say = progress or (lambda message: None)
    variants, roles = [state.variant()], [("base", None, None, 0.0)]
    bounds = {key: (value, lower, upper) for key, value, lower, upper in state.nuisance()}
    for key, value, lower, upper in state.nuisance():
        if ":" in key:
            name, index = key.split(":")
            step = state.added[name][0].parameters[int(index)].step
        else:
            step = FIT_STEP * (upper - lower)
        moved = value + step if value + step <= upper else value - step
        z, values = state.moved(key, moved)
        variants.append(state.variant(z, values))
        roles.append(("nuisance", key, None, moved - value))
    skipped = {}
    shared, aliases = {}, []  # column keys -> the variant's index; (effect, parameter, index) solved by another
    for effect in candidates:
        reason = effect.unavailable_at(fitted, state.added)
        if reason:  # e.g. a refinement of an effect this model does not have (the design's candidates)
            skipped[effect.name] = reason
            continue
        say(f"building the {effect.title} variants")
        built = []
        try:
            with stage(f"building variants: {effect.name}"):
                for j in range(len(effect.parameters)):
                    variant, step = _secant_model(state, effect, j)
                    built.append((variant, j, step))
        except ValueError as error:
            skipped[effect.name] = f"could not be built: {error}"
            continue
        for variant, j, step in built:
            parameter = effect.parameters[j]
            # a secant model another effect shares is the one at the step's usual side
            key = effect.column_key(j) if step == parameter.stepped(parameter.off) - parameter.off else None
            if key is not None and key in shared:  # another effect's secant model: solved once
                aliases.append((effect.name, j, shared[key]))
                continue
            if key is not None:
                shared[key] = len(variants)
            variants.append(variant)
            roles.append(("effect", effect.name, j, step))
    for key, value in (held or {}).items():
        z, values = state.moved(key, value)
        variants.append(state.variant(z, values))
        roles.append(("held", key, None, value))
    say(f"solving {len(variants)} variants")
    if current is None:
        outcomes = solve_variants(variants, fitted.mesh.nodes, fitted.relaxation, fitted.device)
    else:  # the caller's solve of the current model
        outcomes = [current, *(solve_variants(variants[1:], fitted.mesh.nodes, fitted.relaxation, fitted.device)
                               if current.ok else [])]
    solves = sum(outcome.attempts for outcome in outcomes[0 if current is None else 1:])
    base = outcomes[0]
    if not base.ok:
        raise RuntimeError(f"the current model does not solve ({base.status}: {base.message})")
    solves += _retry_nuisance(state, variants, roles, outcomes, bounds, say)
    solves += _retry_effects(state, {e.name: e for e in candidates}, variants, roles, outcomes, say)
    if not isinstance(observations, Observations):  # made from the current model's solve
        observations = observations(base.displacement)
    features = observations.predicted(base.displacement)
    keys = [key for kind, key, _, _ in roles if kind == "nuisance"]
    nuisance = np.zeros((len(features), len(keys)))
    effects: dict[str, np.ndarray] = {}
    fields: dict[str, np.ndarray] = {}
    steps: dict[str, np.ndarray] = {}
    sizes = {e.name: len(e.parameters) for e in candidates}
    for (kind, key, j, step), outcome in zip(roles[1:], outcomes[1:]):
        if kind == "nuisance":
            if not outcome.ok:
                raise RuntimeError(f"the current model with {key} moved does not solve ({outcome.status}: "
                                   f"{outcome.message})")
            nuisance[:, keys.index(key)] = (observations.predicted(outcome.displacement) - features) / step
    # each candidate parameter's column from its secant model's solve (another effect's, where shared)
    columns = [(name, j, i) for i, (kind, name, j, _) in enumerate(roles) if kind == "effect"] + aliases
    for name, j, i in columns:
        outcome, step = outcomes[i], roles[i][3]
        if name in skipped:
            continue
        if not outcome.ok:
            skipped[name] = f"{UNSOLVED} ({outcome.status}: {outcome.message})"
            for table in (effects, fields, steps):
                table.pop(name, None)
            continue
        effects.setdefault(name, np.zeros((len(features), sizes[name])))[:, j] = \
            (observations.predicted(outcome.displacement) - features) / step
        fields.setdefault(name, np.zeros((sizes[name], *base.displacement.shape)))[j] = \
            (outcome.displacement - base.displacement) / step
        steps.setdefault(name, np.zeros(sizes[name]))[j] = step
    solved_held = {key: outcome.displacement if outcome.ok else None
                   for (kind, key, _, _), outcome in zip(roles, outcomes) if kind == "held"}
    return Sensitivities(base.displacement, features, keys, nuisance, effects, fields, steps, skipped, solves,
                         solved_held)


def _secant_model(state: ModelState, effect: Effect, j: int):
    """(variant, step): ``state`` with ``effect``'s parameter ``j`` moved by its step from the off
    value (:meth:`EffectParameter.stepped`); where that model cannot be built (a held plate
    tilted away from the tissue by the step would never touch it), the step to the other side,
    within the range. Raises the first ValueError where neither can be built."""
    parameter = effect.parameters[j]
    tried = [parameter.stepped(parameter.off)]
    other = 2 * parameter.off - tried[0]
    if parameter.lower <= other <= parameter.upper:
        tried.append(other)
    first = None
    for value in tried:
        values = effect.off.copy()
        values[j] = value
        try:
            return state.variant(values={effect.name: (effect, values)}), value - parameter.off
        except ValueError as error:
            first = first or error
    raise first


def _retry_nuisance(state: ModelState, variants, roles, outcomes, bounds, say) -> int:
    """Where a nuisance parameter's moved model failed to solve (an element inverted on the way,
    also with a slower load), the model moved to the other side of its value (within its bounds)
    is solved instead. ``variants``, ``roles`` and ``outcomes`` are updated in place. Returns the
    number of solves made."""
    failed = [i for i, (kind, _, _, _) in enumerate(roles) if kind == "nuisance" and not outcomes[i].ok]
    redo = []
    for i in failed:
        _, key, _, step = roles[i]
        value, lower, upper = bounds[key]
        if lower <= value - step <= upper:
            z, values = state.moved(key, value - step)
            redo.append((i, state.variant(z, values), -step))
    if not redo:
        return 0
    say(f"{len(failed)} nuisance difference(s) failed; solving them to the other side")
    return _solve_again(state, redo, variants, roles, outcomes)


def _retry_effects(state: ModelState, effects: dict[str, Effect], variants, roles, outcomes, say) -> int:
    """Where a candidate's secant model failed to solve (friction that sticks, a stiff skin: an
    element inverted on the way, also with a slower load), the secant to half its step is solved
    instead. ``variants``, ``roles`` and ``outcomes`` are updated in place. Returns the number of
    solves made."""
    redo = []
    for i, (kind, name, j, step) in enumerate(roles):
        if kind != "effect" or outcomes[i].ok:
            continue
        effect = effects[name]
        half = effect.off.copy()
        half[j] = effect.parameters[j].off + step / 2
        redo.append((i, state.variant(values={name: (effect, half)}), step / 2))
    if not redo:
        return 0
    say(f"{len(redo)} candidate secant(s) failed; solving them to half their step")
    return _solve_again(state, redo, variants, roles, outcomes)


def _solve_again(state: ModelState, redo, variants, roles, outcomes) -> int:
    """Solve the ``redo`` list of (index, variant, step) in one batch; where an index's model had
    failed, its replacement takes its place if it solves (variant, outcome and step in
    ``variants``, ``outcomes`` and ``roles``). Returns the number of solves made."""
    fitted = state.fitted
    retried = solve_variants([v for _, v, _ in redo], fitted.mesh.nodes, fitted.relaxation, fitted.device)
    for (i, variant, step), outcome in zip(redo, retried):
        if outcome.ok and not outcomes[i].ok:
            variants[i], outcomes[i] = variant, outcome
            roles[i] = (roles[i][0], roles[i][1], roles[i][2], step)
    return sum(outcome.attempts for outcome in retried)
