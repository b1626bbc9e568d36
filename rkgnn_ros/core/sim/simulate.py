# Copyright 2026 rkgnn_ros maintainers
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""
Accurate simulation of the arm under its servo or replayed torques, sampled into a Dataset.

The ground truth for identification: the plant is integrated by scipy's adaptive solvers
(the ``OdeSolver`` classes behind ``solve_ivp``, stepped here directly so that torque
discontinuities are never stepped over), and only the recorded measurements carry noise.
The servo is the paper's PD or any :class:`~.servo.Servo` (gravity compensation, PID with
its integral as n more states of the loop, torque limits); what is recorded goes through
a :class:`NoiseModel` or a driver's :class:`~.sensors.SensorModel`. A servo can take an
additive feed-forward torque τ_ff(t) (a :class:`~.servo.FeedforwardTrack`, as a servo with
an effort interface applies it), evaluated at the servo's own time.
"""

from dataclasses import dataclass
from typing import Callable, NamedTuple, Optional, Sequence, Union

import numpy as np
from scipy.integrate import BDF, DOP853, LSODA, OdeSolver, Radau, RK23, RK45

from .plant import PlanarArm
from .sensors import SensorModel
from .servo import Servo
from ..data import Dataset

METHODS = {'RK23': RK23, 'RK45': RK45, 'DOP853': DOP853, 'Radau': Radau, 'BDF': BDF,
           'LSODA': LSODA}

#: Default joint speed (rad/s) above which a simulation is declared diverged: far beyond
#: any manipulator, and an unstable loop gets there long before the solver's steps collapse.
MAX_SPEED = 100.0


class SimulationError(RuntimeError):
    """The simulated state became non-finite or unbounded, or the solver failed."""


@dataclass(frozen=True)
class NoiseModel:
    """
    Measurement noise added to the recorded data (never to the plant's true state).

    Attributes
    ----------
    theta_std : float
        Standard deviation of white encoder noise on θ (rad).
    theta_dot_std : float
        Standard deviation of white noise on θ̇ (rad/s); must be 0 when
        ``velocity_from_differences`` is set.
    velocity_from_differences : bool
        If True the recorded θ̇ is not measured but computed from the noisy θ by central
        differences (one-sided first-order at the two ends), as a driver without velocity
        sensing would do; its noise is then about ``theta_std / (√2 dt)``.
    tau_std : float
        Standard deviation of white noise on the recorded torques (N m).

    """

    theta_std: float = 0.0
    theta_dot_std: float = 0.0
    velocity_from_differences: bool = False
    tau_std: float = 0.0

    def __post_init__(self):
        for name in ('theta_std', 'theta_dot_std', 'tau_std'):
            value = float(getattr(self, name))
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f'NoiseModel.{name} must be finite and >= 0, got {value}')
            object.__setattr__(self, name, value)
        if self.velocity_from_differences and self.theta_dot_std > 0.0:
            raise ValueError('NoiseModel.theta_dot_std must be 0 when velocity_from_differences '
                             'is set (the velocity noise then comes from theta_std)')

    @classmethod
    def realistic(cls) -> 'NoiseModel':
        """Return encoder-like noise: θ 1e-4 rad, θ̇ 1e-3 rad/s, exact torques."""
        return cls(theta_std=1e-4, theta_dot_std=1e-3)

    def apply(self, theta: np.ndarray, theta_dot: np.ndarray, tau: Optional[np.ndarray],
              dt: float, rng: np.random.Generator):
        """
        Return noisy copies of the true samples.

        Parameters
        ----------
        theta, theta_dot : ndarray, shape (N, n)
            True joint angles and velocities.
        tau : ndarray, shape (N, n) or None
            True torques.
        dt : float
            Sampling interval, for the finite differences.
        rng : numpy.random.Generator
            Source of the noise.

        Returns
        -------
        theta, theta_dot, tau : ndarray, shape (N, n) (tau None if given None)

        """
        theta = theta + self.theta_std * rng.standard_normal(theta.shape)
        if self.velocity_from_differences:
            theta_dot = np.gradient(theta, dt, axis=0)
        else:
            theta_dot = theta_dot + self.theta_dot_std * rng.standard_normal(theta_dot.shape)
        if tau is not None and self.tau_std > 0.0:
            tau = tau + self.tau_std * rng.standard_normal(tau.shape)
        return theta, theta_dot, tau


def _solver_class(method) -> type:
    if isinstance(method, type) and issubclass(method, OdeSolver):
        return method
    try:
        return METHODS[method]
    except (KeyError, TypeError):
        raise ValueError(f'method must be one of {sorted(METHODS)} or an OdeSolver class, '
                         f'got {method!r}') from None


def _check_state(x: np.ndarray, t: float, max_speed: float, n: int):
    if not np.all(np.isfinite(x)) or np.max(np.abs(x[n:2 * n])) > max_speed:
        raise SimulationError(
            f'simulation diverged at t = {t:.6g} s (state {x}, max_speed {max_speed} rad/s); '
            'the loop is unstable (for a digital controller: is control_rate high enough '
            'for the gains?)')


class _Solver(NamedTuple):
    """The ODE solver of a simulation: its class, tolerances and the speed that diverges."""

    solver_cls: type
    rtol: float
    atol: float
    max_speed: float     # rad/s


def _integrate(fun: Callable, t_a: float, x_a: np.ndarray, t_b: float, t_inner: np.ndarray,
               solver: _Solver, first_step: Optional[float], n: int):
    """
    Integrate ẋ = fun(t, x) from t_a to t_b (x starts with [θ, θ̇] of n joints each).

    Returns x(t_b), the states at ``t_inner`` (shape (M, x.size), t_a < t_inner < t_b, from
    the solver's dense output) and the last step size (to start the next segment with).
    """
    solver_cls, rtol, atol, max_speed = solver
    if first_step is not None:
        first_step = min(first_step, t_b - t_a)
    solver = solver_cls(fun, t_a, x_a, t_b, rtol=rtol, atol=atol, first_step=first_step)
    inner = np.empty((t_inner.size, x_a.size))
    done = 0
    while solver.status == 'running':
        message = solver.step()
        if solver.status == 'failed':
            raise SimulationError(f'solver failed at t = {solver.t:.6g} s: {message}')
        _check_state(solver.y, solver.t, max_speed, n)
        if done < t_inner.size and t_inner[done] <= solver.t:
            stop = int(np.searchsorted(t_inner, solver.t, side='right'))
            inner[done:stop] = solver.dense_output()(t_inner[done:stop]).T
            done = stop
    return solver.y.copy(), inner, solver.step_size


def _piecewise(arm: PlanarArm, x0: np.ndarray, breaks: np.ndarray, t: np.ndarray,
               segment_torque: Callable, solver: _Solver):
    """
    Integrate across segments ``[breaks[j], breaks[j+1]]`` restarting the solver at each.

    ``segment_torque(j, x)`` returns the torque for segment j given the state at its start:
    an (n,) array (held) or a callable ``tau(t)``. ``breaks[0] == t[0]`` and
    ``breaks[-1] == t[-1]``. Returns the true states at the sample times ``t``, (N, 2n).
    """
    tol = 1e-9 * max(1.0, float(np.max(np.abs(t))))
    states = np.empty((t.size, x0.size))
    # samples [first[j], first[j+1]) lie in segment j; a sample within tol of a break is
    # taken to be at it (the state there is known exactly)
    first = np.searchsorted(t, breaks - tol, side='left')
    x, step = x0, None
    for j in range(breaks.size - 1):
        k0, k1 = first[j], first[j + 1]
        if k0 < k1 and abs(t[k0] - breaks[j]) <= tol:
            states[k0] = x
            k0 += 1
        tau = segment_torque(j, x)
        if callable(tau):
            def fun(s, y, tau=tau):
                return arm.dynamics(y, tau(s))
        else:
            def fun(s, y, tau=tau):
                return arm.dynamics(y, tau)
        x, inner, step = _integrate(fun, breaks[j], x, breaks[j + 1], t[k0:k1], solver, step,
                                    arm.n_joints)
        states[k0:k1] = inner
    states[first[-1]:] = x
    return states


def _check_plant(arm) -> None:
    """Refuse anything that is not a plant (a PlanarArm, a UrdfArm: n_joints, dynamics)."""
    if not all(hasattr(arm, name) for name in ('n_joints', 'n_states', 'dynamics')):
        raise TypeError(f'arm must be a plant such as PlanarArm or UrdfArm, got '
                        f'{type(arm).__name__}')


def _sample_times(duration: float, rate: float, t0: float) -> np.ndarray:
    if not (np.isfinite(rate) and rate > 0.0):
        raise ValueError(f'rate must be positive, got {rate}')
    if not (np.isfinite(duration) and duration > 0.0):
        raise ValueError(f'duration must be positive, got {duration}')
    if not np.isfinite(t0):
        raise ValueError(f't0 must be finite, got {t0}')
    return t0 + np.arange(sample_count(duration, rate)) / rate


def sample_count(duration: float, rate: float) -> int:
    """Return the samples of ``duration`` s at ``rate`` Hz, both ends in; at least 2 or raise."""
    n_samples = int(np.floor(duration * rate + 1e-9)) + 1
    if n_samples < 2:
        raise ValueError(f'duration {duration} s at rate {rate} Hz gives fewer than 2 samples')
    return n_samples


def _initial_state(arm: PlanarArm, x0) -> np.ndarray:
    x0 = np.asarray(x0, dtype=float)
    if x0.shape != (arm.n_states,):
        raise ValueError(f'x0 must have shape ({arm.n_states},) = [theta, theta_dot], '
                         f'got {x0.shape}')
    if not np.all(np.isfinite(x0)):
        raise ValueError('x0 must be finite')
    return x0


def _no_feedforward(t):
    """Return None: no feed-forward torque at any time."""
    return None


def _generator(rng) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


def _record(t, states, tau, theta_d, theta_d_dot, noise, rng, joint_names) -> Dataset:
    n = tau.shape[1] if tau is not None else states.shape[1] // 2
    theta, theta_dot = states[:, :n], states[:, n:2 * n]
    if isinstance(noise, SensorModel):
        theta, theta_dot, tau = noise.apply(theta, theta_dot, tau, float(t[1] - t[0]),
                                            _generator(rng))
        if not noise.effort:
            tau = None
        if noise.velocity == 'none':
            theta_dot = np.zeros_like(theta)     # a Dataset needs one: see SensorModel
    elif noise is not None:
        if not isinstance(noise, NoiseModel):
            raise TypeError(f'noise must be a NoiseModel, a SensorModel or None, got '
                            f'{type(noise).__name__}')
        theta, theta_dot, tau = noise.apply(theta, theta_dot, tau, float(t[1] - t[0]),
                                            _generator(rng))
    return Dataset(t=t, theta=theta, theta_dot=theta_dot, tau=tau, theta_d=theta_d,
                   theta_d_dot=theta_d_dot, joint_names=tuple(joint_names or ()))


class SimulationOptions(NamedTuple):
    """The integration, timing and sensor options of :func:`simulate` (see there)."""

    rng: Union[None, int, np.random.Generator] = None
    control_rate: Optional[float] = None
    method: object = None
    rtol: float = 1e-9
    atol: float = 1e-10
    t0: float = 0.0
    joint_names: Optional[Sequence[str]] = None
    max_speed: float = MAX_SPEED
    feedforward: object = None


def simulate(arm: PlanarArm, controller, reference, duration: float, rate: float = 100.0, x0=None,
             noise: Union[None, NoiseModel, SensorModel] = None, **options) -> Dataset:
    """
    Simulate the arm under its servo tracking a reference and sample it.

    Parameters
    ----------
    arm : PlanarArm or UrdfArm
        The plant.
    controller : PDController or Servo
        Anything with ``n_joints`` and ``torque(theta, theta_dot, theta_d, theta_d_dot)``.
        A :class:`~.servo.Servo` with an integral term adds its integral I to the loop's
        states (it starts at 0): continuous, it is integrated with [θ, θ̇]; digital, it
        advances by forward Euler at every tick.
    reference : Reference
        Desired trajectory, ``evaluate(t) -> (theta_d, theta_d_dot)``.
    duration : float
        Simulated time (s); samples at ``t0 + k / rate`` up to ``t0 + duration``.
    rate : float
        Sampling rate of the recorded data (Hz).
    x0 : array_like, shape (2n,), optional
        Initial true state [θ, θ̇]; default on the reference, [θd(t0), θ̇d(t0)].
    noise : NoiseModel or SensorModel, optional
        Noise on the recorded θ, θ̇, τ; the plant and the controller see the true state.
        A :class:`~.sensors.SensorModel` records what a driver publishes (causal
        differenced or filtered velocities); with ``effort=False`` the dataset has no
        ``tau``, and with ``velocity='none'`` its ``theta_dot`` is zeros (a Dataset needs
        one: estimate it from θ, :mod:`rkgnn_ros.core.differentiate`).
    rng : numpy.random.Generator or int, optional
        Randomness of the noise; a fixed seed or generator reproduces the data.
    control_rate : float, optional
        None (default): continuous-time PD. A number: a digital controller that computes
        the torque from the true state at ``t0 + j / control_rate`` and holds it (zero-order
        hold) until its next tick; the solver is restarted at every tick. A digital PD is
        unstable when ``control_rate`` is too low for its gains (roughly when the closed
        loop's fastest eigenvalue exceeds 2 * control_rate). With the paper's gains at
        100 Hz both arm models are unstable (the point-mass arm chatters in a limit cycle
        with joint speeds of hundreds of rad/s, caught by ``max_speed``); they need about
        200 Hz (point masses) and 700 Hz (rods).
    method : str or OdeSolver subclass, optional
        scipy solver, one of :data:`METHODS`. Default: ``'LSODA'`` for a continuous PD (the
        closed loop is mildly stiff, its fastest eigenvalue about 400 to 2000 1/s with the
        paper's gains, and the stiffness-switching LSODA is about eight times cheaper than
        ``'DOP853'`` at these tolerances); ``'RK45'`` for a digital controller, where the
        solver restarts at every tick and a one-step method of moderate order is cheapest.
    rtol, atol : float
        Solver tolerances.
    t0 : float
        Start time (s), also the reference's time origin.
    joint_names : sequence of str, optional
        Names for the dataset's columns.
    max_speed : float
        A true joint speed above this (rad/s) is taken as divergence.
    feedforward : FeedforwardTrack, optional
        An additive feed-forward torque for a :class:`~.servo.Servo`: anything with
        ``evaluate(t) -> τ_ff`` (shape (n,) for a float, (T, n) for an array of times). It
        is added before saturation at the servo's time: continuously, or at each tick of a
        digital servo (then held with the rest of the torque).

    Returns
    -------
    Dataset
        ``t``, measured ``theta`` and ``theta_dot``, ``tau`` (the torque applied at each
        sample instant, feed-forward included: the continuous servo torque, or the held
        digital torque, which at a tick is the newly computed one; saturated if the servo
        is), ``theta_d``, ``theta_d_dot``.

    Raises
    ------
    SimulationError
        If the state becomes non-finite or a joint speed exceeds ``max_speed``.

    """
    (rng, control_rate, method, rtol, atol, t0, joint_names, max_speed, feedforward) = \
        SimulationOptions(**options)
    _check_plant(arm)
    n = arm.n_joints
    if controller.n_joints != n:
        raise ValueError(f'controller has {controller.n_joints} joints, the arm {n}')
    if reference.n_joints != n:
        raise ValueError(f'reference has {reference.n_joints} joints, the arm {n}')
    if feedforward is not None:
        if not isinstance(controller, Servo):
            raise TypeError('a feed-forward needs a Servo (a PDController has no effort '
                            'input; Servo(kp, kd) is the same PD)')
        ff_n = np.shape(feedforward.evaluate(float(t0)))
        if ff_n != (n,):
            raise ValueError(f'the feed-forward gives shape {ff_n}, the arm has {n} joints')
        ff_at = feedforward.evaluate
    else:
        ff_at = _no_feedforward
    if method is None:
        method = 'LSODA' if control_rate is None else 'RK45'
    solver_cls = _solver_class(method)
    t = _sample_times(duration, rate, t0)
    theta_d, theta_d_dot = reference.evaluate(t)
    x0 = (np.concatenate([theta_d[0], theta_d_dot[0]]) if x0 is None
          else _initial_state(arm, x0))

    integral = isinstance(controller, Servo) and controller.has_integral
    if control_rate is None:
        if integral:
            # the servo's integral term is n more states of the loop: x = [θ, θ̇, I]
            def fun(s, x):
                ref, ref_dot = reference.evaluate(s)
                raw, tau = controller.torques(x[:n], x[n:2 * n], ref, ref_dot, x[2 * n:],
                                              ff_at(s))
                return np.concatenate([arm.dynamics(x[:2 * n], tau),
                                       controller.integral_rate(x[:n], ref, raw, tau)])

            x_start = np.concatenate([x0, np.zeros(n)])
        else:
            def fun(s, x):
                ref, ref_dot = reference.evaluate(s)
                if feedforward is None:
                    return arm.dynamics(x, controller.torque(x[:n], x[n:], ref, ref_dot))
                return arm.dynamics(x, controller.torque(x[:n], x[n:], ref, ref_dot, None,
                                                         ff_at(s)))

            x_start = x0
        x_end, inner, _ = _integrate(fun, t[0], x_start, t[-1], t[1:-1],
                                     _Solver(solver_cls, rtol, atol, max_speed), None, n)
        states = np.vstack([x_start, inner, x_end])
        if integral:
            tau = controller.torque(states[:, :n], states[:, n:2 * n], theta_d, theta_d_dot,
                                    states[:, 2 * n:], ff_at(t))
        elif feedforward is not None:
            tau = controller.torque(states[:, :n], states[:, n:], theta_d, theta_d_dot, None,
                                    ff_at(t))
        else:
            tau = controller.torque(states[:, :n], states[:, n:], theta_d, theta_d_dot)
    else:
        if not (np.isfinite(control_rate) and control_rate > 0.0):
            raise ValueError(f'control_rate must be positive, got {control_rate}')
        tol = 1e-9 * max(1.0, abs(t[-1]))
        n_ticks = int(np.floor((t[-1] - t[0]) * control_rate + 1e-9)) + 1
        ticks = t[0] + np.arange(n_ticks) / control_rate
        breaks = ticks.copy() if abs(ticks[-1] - t[-1]) <= tol else np.append(ticks, t[-1])
        breaks[-1] = t[-1]
        tick_tau = np.empty((n_ticks, n))
        # a digital PID advances its integral once per tick (forward Euler, as servos do)
        tick_integral = np.zeros((n_ticks + 1, n))

        def segment_torque(j, x):
            ref, ref_dot = reference.evaluate(ticks[j])
            if integral:
                raw, tick_tau[j] = controller.torques(x[:n], x[n:], ref, ref_dot,
                                                      tick_integral[j], ff_at(ticks[j]))
                rate_j = controller.integral_rate(x[:n], ref, raw, tick_tau[j])
                tick_integral[j + 1] = tick_integral[j] + rate_j / control_rate
            elif feedforward is not None:
                tick_tau[j] = controller.torque(x[:n], x[n:], ref, ref_dot, None,
                                                ff_at(ticks[j]))
            else:
                tick_tau[j] = controller.torque(x[:n], x[n:], ref, ref_dot)
            return tick_tau[j].copy()

        states = _piecewise(arm, x0, breaks, t, segment_torque,
                            _Solver(solver_cls, rtol, atol, max_speed))
        if breaks.size == n_ticks:
            # the last sample is a tick: record the torque computed there
            segment_torque(n_ticks - 1, states[-1])
        tau = tick_tau[np.searchsorted(ticks, t + tol, side='right') - 1]
    return _record(t, states, tau, theta_d, theta_d_dot, noise, rng, joint_names)


class OpenLoopOptions(NamedTuple):
    """The integration and sensor options of :func:`simulate_open_loop` (see there)."""

    method: object = 'RK45'
    rtol: float = 1e-9
    atol: float = 1e-10
    noise: Optional[NoiseModel] = None
    rng: Union[None, int, np.random.Generator] = None
    joint_names: Optional[Sequence[str]] = None
    max_speed: float = MAX_SPEED


def simulate_open_loop(arm: PlanarArm, tau_samples, t, x0, hold: bool = True, **options
                       ) -> Dataset:
    """
    Play recorded torques into the arm open loop (the 'true model' rollout).

    Parameters
    ----------
    arm : PlanarArm or UrdfArm
        The plant.
    tau_samples : array_like, shape (N, n)
        Torques at the sample times.
    t : array_like, shape (N,)
        Uniformly spaced, increasing sample times (s).
    x0 : array_like, shape (2n,)
        True state [θ, θ̇] at ``t[0]``.
    hold : bool
        True (default): zero-order hold, ``tau_samples[k]`` acts on ``[t[k], t[k+1])``.
        False: linear interpolation between consecutive samples.
    method : str or OdeSolver subclass
        scipy solver; restarted at every sample, so a one-step method (default
        ``'RK45'``) suits best.
    rtol, atol : float
        Solver tolerances.
    noise : NoiseModel, optional
        Noise on the recorded θ, θ̇ and τ.
    rng : numpy.random.Generator or int, optional
        Randomness of the noise.
    joint_names : sequence of str, optional
        Names for the dataset's columns.
    max_speed : float
        A joint speed above this (rad/s) raises :class:`SimulationError`.

    Returns
    -------
    Dataset
        With ``tau`` the given (noise-free unless ``noise.tau_std``) torques and no
        desired trajectory.

    """
    method, rtol, atol, noise, rng, joint_names, max_speed = OpenLoopOptions(**options)
    _check_plant(arm)
    n = arm.n_joints
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.size < 2 or not np.all(np.isfinite(t)):
        raise ValueError(f't must be a finite 1-D array of at least 2 samples, got {t.shape}')
    steps = np.diff(t)
    if np.any(steps <= 0.0) or not np.allclose(steps, steps[0], rtol=1e-6, atol=1e-9):
        raise ValueError('t must be strictly increasing and uniformly spaced')
    tau_samples = np.asarray(tau_samples, dtype=float)
    if tau_samples.shape != (t.size, n):
        raise ValueError(f'tau_samples must have shape ({t.size}, {n}), got {tau_samples.shape}')
    if not np.all(np.isfinite(tau_samples)):
        raise ValueError('tau_samples must be finite')
    x0 = _initial_state(arm, x0)
    solver_cls = _solver_class(method)

    def segment_torque(j, x):
        if hold:
            return tau_samples[j]
        t_a, slope = t[j], (tau_samples[j + 1] - tau_samples[j]) / (t[j + 1] - t[j])
        return lambda s: tau_samples[j] + slope * (s - t_a)

    states = _piecewise(arm, x0, t, t, segment_torque, _Solver(solver_cls, rtol, atol, max_speed))
    return _record(t, states, tau_samples.copy(), None, None, noise, rng, joint_names)
