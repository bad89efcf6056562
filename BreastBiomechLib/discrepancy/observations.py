"""What the diagnosis compares between the model and the measured case: features computed from
the fitting mesh's nodal displacement, their measured values and their noise.

Channels (each feature one number, mm):

- ``landmarks``: the L, P, S coordinates of each landmark moved by the displacement, against the
  landmarks marked in the compressed image;
- ``surface``: the signed distance (> 0 outside) of breast-skin nodes, moved, to the body surface
  of the measured image (the nodes thinned to one per ``surface_spacing_mm`` cell, so that
  neighbouring features are not the same measurement twice; nodes on the field-of-view cut and
  outside the image left out), against 0.

The noise of a feature is what it would scatter by with nothing missing from the model: the
landmarks' localisation error and, for the surface, the voxels' quantisation (largest spacing /
sqrt(12)), each with a model-error floor (the fitting mesh's discretisation and the
segmentation's error, which no effect explains) added in quadrature. Features are taken as
independent.

A fit of several measured states has these features in every state (each state's own measured
image, landmarks and noise), stacked first state first; a further state's labels start with its
name ("lateral: nipple L"), and :attr:`Observations.state` says each feature's state. Their
:meth:`Observations.predicted` takes the states' displacements stacked
(:meth:`~BreastBiomechLib.discrepancy.fitted.FittedCase.split`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from BreastBiomechLib.io.case_layout import FIRST_STATE
from BreastBiomechLib.landmarks import LandmarkMapper
from BreastBiomechLib.timing import staged

CHANNELS = ("landmarks", "surface")
FLOORS = ("measured", "fixed")  # the model-error floor measured from the case (lower bound model_sd_mm), or fixed


@dataclass
class NoiseModel:
    """The noise the diagnosis assumes (mm, one standard deviation per coordinate):
    ``landmark_sd_mm`` the landmarks' localisation error, ``model_sd_mm`` the model-error floor
    added to every feature (with ``floor`` "measured", the lower bound of the floor measured
    from the case: :mod:`~BreastBiomechLib.discrepancy.floor`; "fixed": the floor itself),
    ``surface_spacing_mm`` the thinning of the surface features, and the ``channels`` used."""

    landmark_sd_mm: float = 0.5
    model_sd_mm: float = 0.5
    surface_spacing_mm: float = 8.0
    channels: tuple[str, ...] = CHANNELS
    floor: str = "measured"

    def __post_init__(self) -> None:
        if not (self.landmark_sd_mm >= 0 and self.model_sd_mm >= 0 and self.surface_spacing_mm > 0):
            raise ValueError("the noise model needs landmark_sd_mm >= 0, model_sd_mm >= 0, surface_spacing_mm > 0")
        if self.floor not in FLOORS:
            raise ValueError(f"the model-error floor is one of {FLOORS}, not {self.floor!r}")
        unknown = set(self.channels) - set(CHANNELS)
        if unknown or not self.channels:
            raise ValueError(f"channels are some of {CHANNELS}, not {sorted(unknown) or 'none'}")


@dataclass
class Observations:
    """``n`` features: their ``labels``, ``channel`` names, ``measured`` values, noise ``sigma``
    (mm) and reference ``points`` (N, 3) LPS mm (where in the undeformed breast each feature
    sits, for the regions), ``floor_mm`` the fixed model-error floor inside ``sigma`` (0 where
    none was assumed), ``measurement_sd`` (n,) mm the part of ``sigma`` that is measurement (the
    landmarks' localisation, the surface's quantisation) and ``floor`` (n,) mm each feature's
    measured floor where one was measured (:meth:`with_floor`), ``state`` (n,) the measured
    state each feature belongs to (None: every feature the first state's). :meth:`predicted`
    computes the features from a displacement."""

    labels: list[str]
    channel: np.ndarray
    measured: np.ndarray
    sigma: np.ndarray
    points: np.ndarray
    _parts: list = field(default_factory=list, repr=False)
    floor_mm: float = 0.0
    measurement_sd: np.ndarray | None = None
    floor: np.ndarray | None = None
    state: np.ndarray | None = None

    def in_state(self, name: str) -> np.ndarray:
        """Which features (n,) bool belong to measured state ``name``."""
        if self.state is None:
            return np.full(len(self), name == FIRST_STATE)
        return self.state == name

    @property
    def base_sigma(self) -> np.ndarray:
        """Each feature's noise (n,) mm with the fixed floor ``floor_mm`` (what ``sigma`` is when
        no floor was measured)."""
        return self.sigma if self.measurement_sd is None else np.hypot(self.measurement_sd, self.floor_mm)

    @property
    def feature_floor(self) -> np.ndarray:
        """Each feature's model-error floor (n,) mm: the measured one, else the fixed one."""
        return self.floor if self.floor is not None else np.full(len(self), self.floor_mm)

    def with_floor(self, floor: np.ndarray) -> "Observations":
        """These features with each one's model-error floor ``floor`` (n,) mm in place of the fixed
        one: sigma = sqrt(measurement_sd^2 + floor^2)."""
        floor = np.asarray(floor, float)
        if floor.shape != self.measured.shape or self.measurement_sd is None:
            raise ValueError(f"a floor for {len(self)} features made by observations_of is needed, not "
                             f"{floor.shape[0] if floor.ndim else 'a scalar'}")
        return replace(self, sigma=np.hypot(self.measurement_sd, floor), floor=floor)

    def __len__(self) -> int:
        return len(self.measured)

    @staged("features")
    def predicted(self, displacement_mm: np.ndarray) -> np.ndarray:
        """The features (n,) of nodal displacements (N, 3) mm of the fitting mesh."""
        return np.concatenate([part(displacement_mm) for part in self._parts])

    def residual(self, displacement_mm: np.ndarray) -> np.ndarray:
        """Measured minus predicted features (n,), mm."""
        return self.measured - self.predicted(displacement_mm)


def thinned(points: np.ndarray, spacing_mm: float) -> np.ndarray:
    """Indices of ``points`` keeping the first in each cube of ``spacing_mm``."""
    cells = np.floor(np.asarray(points, float) / spacing_mm).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return np.sort(first)


@staged("features")
def observations_of(fitted, base_displacement: np.ndarray, noise: NoiseModel | None = None) -> Observations:
    """The features of ``fitted`` (a :class:`~BreastBiomechLib.discrepancy.fitted.FittedCase`)
    in the channels of ``noise``, the surface features chosen where the fit's solution
    ``base_displacement`` (N, 3) mm puts them inside the measured image; in a fit of several
    measured states, every state's features stacked (``base_displacement`` (S N, 3), the
    states' solutions one after the other)."""
    noise = noise or NoiseModel()
    if not fitted.further:
        return _state_observations(fitted, base_displacement, noise)
    n = len(fitted.mesh.nodes)
    parts = [_state_observations(state, u, noise, prefix=k > 0)
             for k, (state, u) in enumerate(zip(fitted.states, fitted.split(base_displacement)))]

    def sliced(part, k):
        return lambda u: part(u[k * n:(k + 1) * n])

    return Observations(
        [label for o in parts for label in o.labels], np.concatenate([o.channel for o in parts]),
        np.concatenate([o.measured for o in parts]), np.concatenate([o.sigma for o in parts]),
        np.concatenate([o.points for o in parts]),
        [sliced(part, k) for k, o in enumerate(parts) for part in o._parts], noise.model_sd_mm,
        np.concatenate([o.measurement_sd for o in parts]),
        state=np.concatenate([np.full(len(o), state.name) for o, state in zip(parts, fitted.states)]))


def _state_observations(fitted, base_displacement: np.ndarray, noise: NoiseModel, prefix: bool = False) -> Observations:
    """The features of one measured state ``fitted`` (labels starting with its name where ``prefix``)."""
    from BreastBiomechLib.similarity.surface import SurfaceDistance

    mesh = fitted.mesh
    named = f"{fitted.name}: " if prefix else ""
    labels, channel, measured, measurement, points, parts = [], [], [], [], [], []
    if "landmarks" in noise.channels and fitted.reference is not None:
        mapper = LandmarkMapper(mesh, fitted.reference)
        for name in fitted.reference.labels:
            labels += [f"{named}{name} {axis}" for axis in "LPS"]
        n = 3 * len(fitted.reference.labels)
        channel += ["landmarks"] * n
        measured.append(fitted.measured.positions.ravel())
        measurement.append(np.full(n, noise.landmark_sd_mm))
        points.append(np.repeat(fitted.reference.positions, 3, axis=0))
        parts.append(lambda u: mapper.map(u).positions.ravel())
    if "surface" in noise.channels:
        surface = SurfaceDistance(fitted.measured_image)
        skin = mesh.node_set("breast_skin")
        if "fov_cut" in mesh.point_data:
            skin = np.setdiff1d(skin, mesh.node_set("fov_cut"))
        skin = skin[thinned(mesh.nodes[skin], noise.surface_spacing_mm)]
        base = surface.signed_distances(mesh.nodes[skin] + base_displacement[skin])
        keep = np.isfinite(base)
        skin, base = skin[keep], base[keep]
        if len(skin):
            quantisation = max(fitted.measured_image.GetSpacing()) / np.sqrt(12.0)
            labels += [f"{named}skin node {i}" for i in skin]
            channel += ["surface"] * len(skin)
            measured.append(np.zeros(len(skin)))
            measurement.append(np.full(len(skin), quantisation))
            points.append(mesh.nodes[skin])

            def signed(u, skin=skin, base=base):
                values = surface.signed_distances(mesh.nodes[skin] + u[skin])
                return np.where(np.isfinite(values), values, base)  # left the image: no information

            parts.append(signed)
    if not parts:
        raise ValueError(f"no feature to compare{f' in state {fitted.name}' if prefix else ''}: the case has no "
                         "landmarks and no breast skin inside the measured image; add landmarks or check the fit's "
                         "mesh and the measured image")
    measurement = np.concatenate(measurement)
    return Observations(labels, np.array(channel), np.concatenate(measured), np.hypot(measurement, noise.model_sd_mm),
                        np.concatenate(points), parts, noise.model_sd_mm, measurement)
