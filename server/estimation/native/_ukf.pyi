# The compiled module's interface (bindings.cc), for mypy; arrays are float64 copies both ways.

import numpy as np

MUJOCO_HEADER_VERSION: int

def mujoco_version() -> int: ...

class SingularMatrix(Exception): ...
class AdapterState: ...

class Adapter:
    def __init__(
        self,
        *,
        r0: np.ndarray,
        q0: np.ndarray,
        adapt_q: list[bool],
        inflate: bool,
        bounds: dict[str, float],
        nis_limit: float,
    ) -> None: ...
    def reset(self) -> None: ...
    def observe(
        self, *, innovation: np.ndarray, consecutive: bool, gain: np.ndarray, nis: float, noise_share: float
    ) -> tuple[bool, bool]: ...
    def observe_gap(self, *, nis: float, m: int) -> None: ...
    def absorbed(self) -> None: ...
    def q_for(self, q0: np.ndarray) -> np.ndarray: ...
    window_full: bool
    r_diagonal: np.ndarray
    scale: np.ndarray
    inflation: float
    gap_inflation: float
    def snapshot(self) -> AdapterState: ...
    def restore(self, state: AdapterState) -> None: ...

class Ukf:
    def __init__(
        self,
        model_address: int,
        *,
        n: int,
        size: int,
        fblocks: int,
        controlled: bool,
        scheme: int,
        scale: float,
        unit: np.ndarray,
        wm: np.ndarray,
        wc: np.ndarray,
        z_index: list[int],
        nstep: int,
        inputs: int,
    ) -> None: ...
    def predict(self) -> None: ...
    def update(self, z: np.ndarray) -> None: ...
    def sigma_points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray: ...
    def propagate(self, sigmas: np.ndarray, nstep: int) -> np.ndarray: ...
    def tidy(self) -> bool: ...
    def largest_variance(self) -> float: ...
    def forward(
        self, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray, ctrl: np.ndarray, qfrc: np.ndarray
    ) -> np.ndarray: ...
    nis: float
    nsigma: int
    nstep: int
    repairs: int
    sigmas_f: np.ndarray
    x: np.ndarray
    P: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    act: np.ndarray
    ctrl: np.ndarray
    qfrc: np.ndarray
    y: np.ndarray
    K: np.ndarray
    S: np.ndarray
    SI: np.ndarray
    propagated_act: np.ndarray

class CombinerState:
    nbytes: int

class PriorTable:
    def __init__(
        self,
        *,
        rate: float,
        q: np.ndarray,
        v: np.ndarray,
        last: np.ndarray,
        rows: np.ndarray,
        features: np.ndarray,
        spread: np.ndarray,
    ) -> None: ...
    candidates: int

class Combiner:
    def __init__(
        self,
        model_address: int,
        *,
        dt: float,
        steps_per_tick: int,
        horizon: int,
        legs: list[tuple[PriorTable, list[int], list[float]]] = ...,
        prior_cov: list[np.ndarray] = ...,
        prior_cov_v: list[np.ndarray] = ...,
    ) -> None: ...
    def reset(self) -> None: ...
    def advance(self) -> None: ...
    def observe(
        self,
        qpos: np.ndarray,
        qvel: np.ndarray,
        *,
        mean_qpos: np.ndarray,
        mean_qvel: np.ndarray,
        act: np.ndarray,
        force: np.ndarray,
        rate: np.ndarray | None,
    ) -> None: ...
    def forecast(
        self, *, noise_q: np.ndarray | None, noise_qd: np.ndarray | None, ended: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None: ...
    def fill_window(self, q: np.ndarray, v: np.ndarray) -> int: ...
    def snapshot(self) -> CombinerState: ...
    def restore(self, state: CombinerState) -> None: ...
    horizon: int
    predictors: int
    nv: int
    na: int
    window: int
    tick: int

# The linearised filter (linearised.h).
class Ekf:
    def __init__(
        self,
        model_address: int,
        linearised_address: int,
        *,
        driven: bool,
        nstep: int,
        Q: np.ndarray,
        R: np.ndarray,
        eps: float,
        force_eps: float,
    ) -> None: ...
    def predict(
        self, x: np.ndarray, P: np.ndarray, act: np.ndarray, qfrc: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...
    def update(self, x: np.ndarray, P: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]: ...
    n: int

class TickState:
    @property
    def nbytes(self) -> int: ...

class Tick:
    def __init__(
        self,
        ukf: Ukf,
        *,
        adapter: Adapter | None,
        combiner: Combiner | None,
        act_low: np.ndarray,
        act_high: np.ndarray,
        covariance_limit: float,
        force: int,
    ) -> None: ...
    def advance(self, gap: bool) -> tuple[bool, float, bool, np.ndarray]: ...
    def step(
        self, z: np.ndarray, *, quiet: bool, qvel: np.ndarray | None
    ) -> tuple[
        bool,
        bool,
        float,
        float,
        bool,
        bool,
        bool,
        np.ndarray,
        np.ndarray,
        np.ndarray,
        np.ndarray | None,
        bool,
    ]: ...
    def snapshot(self) -> TickState: ...
    def restore(self, state: TickState) -> None: ...
