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
Reproduce the paper: identify its 3-link arm in cases 1, 2 and 3 (``make paper``).

For each case, two runs on the same 10 s of data (the paper's PD-controlled arm following
``paper_reference``, 100 Hz):

- ``paper_ea``: the paper's structure (``NetworkSpec.paper``: 99 / 99 / 153 genome elements)
  and its EA (tournament 6, 100% mutation, 20% crossover, 100 individuals, 200 generations),
  torque held between samples (case 1);
- ``best``: our default structure and pipeline (``fit_best``: the global network on the
  trigonometric basis, its closed-form fit, Levenberg-Marquardt on the rollouts over the
  arm's coefficients, then CMA-ES over them, the stage chosen on the newest 20 % of the
  data) in a wall-time budget; its J is on the older 80 % it fits.

Each model is then rolled out open loop for 10 s on a held-out reference
(``heldout_reference``) that neither saw. Writes ``paper.json``, ``paper.md`` and figures
like the paper's Figs. 9-14 (measured vs identified trajectories, evolutionary history) to
``bench/results``. Also tunes the PD gains with the same EA (eq. 10) when
``rkgnn_ros.core.sim.tuning`` is available.
"""

import argparse
import datetime
import json
import os
import platform
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from rkgnn_ros.core.fitting.identify import Evolution, fit_best, nrmse  # noqa: E402
from rkgnn_ros.core.fitting.optimizers import PaperEA  # noqa: E402
from rkgnn_ros.core.model.spec import NetworkSpec  # noqa: E402
from rkgnn_ros.core.sim.plant import PDController, PlanarArm  # noqa: E402
from rkgnn_ros.core.sim.simulate import simulate  # noqa: E402
from rkgnn_ros.core.sim.trajectories import heldout_reference, paper_reference  # noqa: E402

CASES = {'1': 'torque', '2': 'pd_gains', '3': 'unknown'}
TITLES = {'1': 'case 1: torque known', '2': 'case 2: PD gains known',
          '3': 'case 3: nothing known about the controller'}


def make_data(duration=10.0, rate=100.0):
    """Return the fitting and held-out datasets of the paper's arm under its PD."""
    arm = PlanarArm.paper()
    pd = PDController.paper()
    fit_data = simulate(arm, pd, paper_reference(3), duration, rate=rate)
    held = simulate(arm, pd, heldout_reference(3), duration, rate=rate)
    return fit_data, held, np.diag(pd.kp), np.diag(pd.kd)


def spread_settings(spread, floor=0.02, floor_generation=150):
    """
    Return PaperEA settings whose first generation and mutation both start at ``spread``.

    The spread decays geometrically to ``floor`` (at most ``spread``) at ``floor_generation``
    and stays there, as the default schedule does.
    """
    floor = min(floor, spread)
    return {'population_size': 100, 'sigma': spread, 'init_scale': spread, 'sigma_min': floor,
            'sigma_decay': (floor / spread) ** (1.0 / floor_generation)}


def spread_study(cases, spreads, seeds, generations, fit_data, held, kp, kd, log):
    """Return {case: {spread: [per-seed results]}} of the paper EA at each initial spread."""
    out = {}
    for case in cases:
        out[case] = {}
        for spread in spreads:
            runs = []
            for seed in seeds:
                run = run_paper_ea(case, fit_data, kp, kd, generations, seed,
                                   lambda msg: None, spread_settings(spread))
                history, wall = run['history'], run['wall_s']
                runs.append({'seed': seed, 'start_cost': run['start_cost'],
                             'final_cost': run['final_cost'],
                             'first_generation_finite': history[0]['finite'],
                             'best_cost_every_20': [h['best_cost'] for h in history
                                                    if h['generation'] % 20 == 0],
                             'heldout_nrmse': nrmse(run['model'].predict(held)[:, :3],
                                                    held.theta),
                             'wall_s': wall})
                log(f"  case {case} spread {spread:g} seed {seed}: J {runs[-1]['final_cost']:.4g}"
                    f"  first generation {runs[-1]['first_generation_finite']} finite  "
                    f"held-out {_percent(runs[-1]['heldout_nrmse'])}  {wall:.0f} s")
            out[case][str(spread)] = runs
    return out


def run_paper_ea(case, fit_data, kp, kd, generations, seed, log, settings=None):
    """
    Run the paper's structure and EA; return its run (model, history, start_cost, ...).

    ``settings`` default to :class:`PaperEA`'s (the paper's operators, 100 individuals,
    the start genome in the first generation).
    """
    spec = NetworkSpec.paper(3, CASES[case])
    evo = Evolution(spec, fit_data, 'paper', settings or {'population_size': 100}, seed, kp,
                    kd, torque_interpolation='hold')
    start_cost = float(evo.problem.cost(evo.optimizer.x0[None])[0])
    history = []
    t0 = time.perf_counter()
    for _ in range(generations):
        stats = evo.step()
        stats['wall_s'] = time.perf_counter() - t0
        history.append(stats)
        if stats['generation'] % 20 == 0 or stats['generation'] == 1:
            log(f"  case {case} paper EA  gen {stats['generation']:4d}  "
                f"best J {stats['best_cost']:.4g}  mean J {stats['mean_cost']:.4g}  "
                f"diverged {stats['population'] - stats['finite']:3d}  "
                f"spread {stats['spread']:.3g}  {stats['wall_s']:.0f} s")
    return {'model': evo.best_model(fit_data.joint_names), 'history': history,
            'wall_s': time.perf_counter() - t0, 'evaluations': history[-1]['evaluations'],
            'final_cost': history[-1]['best_cost'], 'start_cost': start_cost}


def paper_ea_description(generations=200):
    """Describe the paper EA's settings as :class:`PaperEA` has them by default."""
    s = PaperEA.DEFAULTS
    spread = s['sigma'] if s['init_scale'] is None else s['init_scale']
    return (f"tournament {s['tournament_size']}, {s['mutation_rate']:.0%} mutation, "
            f"{s['crossover_rate']:.0%} crossover (BLX-{s['blx_alpha']:g}), "
            f"{s['population_size']} individuals × {generations} generations, "
            f"{s['n_elite']} elite; the first generation holds the start genome and "
            f"{s['population_size'] - 1} individuals around it at the initial spread "
            f"{spread:g}, the mutation spread starts at {s['sigma']:g} and shrinks by "
            f"{s['sigma_decay']:g} per generation to its floor {s['sigma_min']:g}")


def compact_history(name, history):
    """Return the per-generation (and per-stage) figures of a run's history for the JSON."""
    def series(entries):
        return {'best_cost': [h['best_cost'] for h in entries],
                'mean_cost_finite': [h['mean_cost'] if h['finite'] else None
                                     for h in entries],
                'diverged': [h['population'] - h['finite'] for h in entries]}
    if name == 'paper_ea':
        return series(history)
    keys = ('phase', 'shooting', 'cost', 'kept', 'best_cost', 'evaluations', 'wall_s')
    cma = [h for h in history if h['phase'] == 'cmaes']
    return {'stages': [{k: h[k] for k in keys if k in h} for h in history
                       if h['phase'] != 'cmaes'],
            'cmaes': dict(series(cma), wall_s=[h['wall_s'] for h in cma])}


def plot_case(case, fit_data, held, runs, out_dir):
    """Write the trajectory and evolution figures of one case; return their paths."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    paths = []
    fig, axes = plt.subplots(3, 2, figsize=(12, 8), sharex=True)
    for col, (data, label) in enumerate(((fit_data, 'fitting data'),
                                         (held, 'held-out reference'))):
        for j in range(3):
            ax = axes[j, col]
            ax.plot(data.t, data.theta[:, j], 'k', lw=2, label='measured')
            ax.plot(data.t, data.theta_d[:, j], color='0.6', lw=1, ls=':', label='desired')
            for name, style in (('paper_ea', 'C1--'), ('best', 'C0-')):
                pred = runs[name]['model'].predict(data)
                ax.plot(data.t, pred[:, j], style, lw=1.2, label=f'identified ({name})')
            lo, hi = data.theta[:, j].min(), data.theta[:, j].max()
            pad = 0.5 * (hi - lo) + 0.05
            ax.set_ylim(lo - pad, hi + pad)  # a diverged rollout leaves the frame
            ax.set_ylabel(f'θ{j + 1} [rad]')
            if j == 0:
                ax.set_title(f'{TITLES[case]}: {label}')
            ax.grid(alpha=0.3)
        axes[-1, col].set_xlabel('t [s]')
    axes[0, 0].legend(fontsize=8, loc='best')
    fig.tight_layout()
    path = os.path.join(out_dir, f'case{case}_trajectories.png')
    fig.savefig(path, dpi=90)
    plt.close(fig)
    paths.append(path)

    path = os.path.join(out_dir, f'case{case}_evolution.png')
    plot_evolution(case, runs, path)
    paths.append(path)
    return paths


#: Colours of the stages of our pipeline in the evolution figures.
STAGE_COLOURS = {'start': '0.5', 'equation': 'C2', 'linear': 'C2', 'lm': 'C4', 'cmaes': 'C0'}


def plot_evolution(case, runs, path):
    """
    Write the evolutionary histories of one case, like the paper's Figs. 10, 12 and 14.

    Left: the paper EA per generation, the best J so far and the mean J of the generation's
    finite individuals (the mean over all is infinite while any diverges), the J of its
    start genome, and below the number of diverged individuals. Right: our pipeline's best J
    so far against wall time, each stage's results marked, with CMA-ES's per-generation mean
    and diverged count.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 2, figsize=(12, 6), sharex='col',
                             gridspec_kw={'height_ratios': [3, 1]})
    run = runs['paper_ea']
    hist = run['history']
    gens = [h['generation'] for h in hist]
    ax = axes[0, 0]
    ax.semilogy(gens, [h['best_cost'] for h in hist], 'C1', lw=2, label='best so far')
    ax.semilogy(gens, [h['mean_cost'] if h['finite'] else np.nan for h in hist], 'C1',
                alpha=0.45, label='mean of the finite individuals')
    if np.isfinite(run['start_cost']):
        ax.axhline(run['start_cost'], color='0.4', ls='--', lw=1,
                   label=f"start genome (J {run['start_cost']:.3g})")
    else:
        ax.plot([], [], ' ', label='start genome diverges')
    ax.set_title(f'{TITLES[case]}: paper structure and EA')
    ax.set_ylabel('J')
    ax.legend(fontsize=8)
    axes[1, 0].step(gens, [h['population'] - h['finite'] for h in hist], 'C3', where='mid')
    axes[1, 0].set_ylim(0, max(h['population'] for h in hist) * 1.05)
    axes[1, 0].set_ylabel('diverged')
    axes[1, 0].set_xlabel('generation')

    hist = runs['best']['history']
    ax = axes[0, 1]
    ax.semilogy([h['wall_s'] for h in hist], [h['best_cost'] for h in hist], 'k',
                drawstyle='steps-post', lw=2, label='best so far (the result)')
    for phase, colour in STAGE_COLOURS.items():
        entries = [h for h in hist if h['phase'] == phase and np.isfinite(h['cost'])]
        if phase == 'cmaes':
            cma = [h for h in hist if h['phase'] == 'cmaes']
            ax.semilogy([h['wall_s'] for h in cma],
                        [h['mean_cost'] if h['finite'] else np.nan for h in cma], colour,
                        alpha=0.45, label='CMA-ES mean of the finite individuals')
            if cma:
                ax.axvline(cma[0]['wall_s'], color=colour, ls=':', lw=1)
        elif entries:
            ax.semilogy([h['wall_s'] for h in entries], [h['cost'] for h in entries], 'o',
                        color=colour, label=f'{phase}: J of its result')
    first = 'closed form' if any(h['phase'] == 'linear' for h in hist) else 'equation error'
    ax.set_title(f'{TITLES[case]}: ours ({first}, LM, CMA-ES)')
    ax.set_ylabel('J')
    ax.legend(fontsize=8)
    cma = [h for h in hist if h['phase'] == 'cmaes']
    axes[1, 1].step([h['wall_s'] for h in cma], [h['population'] - h['finite'] for h in cma],
                    'C3', where='mid')
    axes[1, 1].set_ylabel('diverged (CMA-ES)')
    axes[1, 1].set_xlabel('wall time [s]')
    for ax in axes.ravel():
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


#: The PD tuning study: (servo rate in Hz, None for the continuous PD; torque limit as a
#: multiple of the paper loop's peak torque per joint on the same reference, rounded up to
#: 0.5 N m, None for none), in the order they are run.
PD_STUDY = ((200.0, None), (200.0, 1.0), (1000.0, 1.0), (100.0, None), (None, None),
            (200.0, 0.75), (1000.0, None), (100.0, 1.0))

#: Coordinate scans of the study: each gain swept over its range (41 values) with the
#: others at the paper's, for these (servo rate, torque limit factor) pairs.
PD_SCANS = ((None, None), (1000.0, None), (200.0, None), (100.0, None), (200.0, 1.0),
            (200.0, 0.75))


def peak_torque(arm, reference, duration=10.0):
    """Return the paper loop's peak |τ| per joint on ``reference``, rounded up to 0.5 N m."""
    data = simulate(arm, PDController.paper(), reference, duration, rate=100.0)
    return np.ceil(2.0 * np.abs(data.tau).max(axis=0)) / 2.0


def tune_gains(generations, log, servo_rate=None, torque_limit=None, seed=0):
    """
    Tune the PD gains with the paper's EA (eq. 10, 60 individuals); return a dict.

    ``servo_rate`` None: the continuous PD of ``rkgnn_ros.core.sim.tuning``; otherwise the
    digital servo of ``tuning_study`` at that rate (Hz), saturated at ``torque_limit``.
    """
    from rkgnn_ros.core.sim.tracking import DEFAULT_BOUNDS
    from rkgnn_ros.core.sim.tuning import tune_pd_gains
    from rkgnn_ros.core.sim.tuning_study import SampledTrackingProblem
    arm, reference = PlanarArm.paper(), paper_reference(3)
    problem = (None if servo_rate is None else
               SampledTrackingProblem(arm, reference, 10.0, servo_rate, torque_limit))
    result = tune_pd_gains(arm, reference, duration=10.0, population_size=60,
                           generations=generations, seed=seed, problem=problem)
    (kp_lo, kp_hi), (kd_lo, kd_hi) = DEFAULT_BOUNDS
    gains = np.concatenate([result.kp, result.kd])
    hi = np.array([kp_hi] * 3 + [kd_hi] * 3)
    out = {'servo_rate_hz': servo_rate,
           'torque_limit_nm': None if torque_limit is None else np.asarray(
               torque_limit, dtype=float).tolist(),
           'seed': seed, 'kp_found': np.asarray(result.kp).tolist(),
           'kd_found': np.asarray(result.kd).tolist(), 'cost_found': float(result.cost),
           'kp_paper': [32.84, 42.05, 42.31], 'kd_paper': [42.44, 0.19, 4.86],
           'cost_paper_gains': float(result.paper_cost),
           'at_upper_bound': (gains >= 0.99 * hi).tolist(),
           'bounds': [[kp_lo, kp_hi], [kd_lo, kd_hi]],
           'best_cost_every_20': result.history[19::20, 0].tolist(),
           'evaluations': int(result.evaluations), 'step_s': float(result.step),
           'wall_s': float(result.wall_s)}
    servo = 'continuous PD' if servo_rate is None else f'{servo_rate:g} Hz servo'
    log(f"  PD tuning ({servo}, torque limit {out['torque_limit_nm']}): "
        f"Kp {np.round(out['kp_found'], 2)} Kd {np.round(out['kd_found'], 2)} "
        f"cost {out['cost_found']:.4g} (paper's gains: {out['cost_paper_gains']:.4g}), "
        f"{out['wall_s']:.0f} s")
    return out


def coordinate_scan(servo_rate, torque_limit, points=41):
    """
    Sweep each gain over its bounds with the others at the paper's; return one dict per gain.

    Says, gain by gain, whether eq. (10) has its minimum near the published value under the
    given servo: the value of the sweep's minimum, its cost and the paper's.
    """
    from rkgnn_ros.core.sim.tracking import DEFAULT_BOUNDS, TrackingProblem
    from rkgnn_ros.core.sim.tuning import paper_gains
    from rkgnn_ros.core.sim.tuning_study import SampledTrackingProblem
    arm, reference = PlanarArm.paper(), paper_reference(3)
    problem = (TrackingProblem(arm, reference, 10.0) if servo_rate is None else
               SampledTrackingProblem(arm, reference, 10.0, servo_rate, torque_limit))
    paper = paper_gains()
    (_, kp_hi), (_, kd_hi) = DEFAULT_BOUNDS
    out = []
    for i, name in enumerate(['Kp1', 'Kp2', 'Kp3', 'Kd1', 'Kd2', 'Kd3']):
        values = np.linspace(0.0, kp_hi if i < 3 else kd_hi, points)
        gains = np.tile(paper, (points, 1))                                  # (points, 6)
        gains[:, i] = values
        cost = problem.cost(gains)
        k = int(np.argmin(cost))
        out.append({'gain': name, 'paper': float(paper[i]), 'argmin': float(values[k]),
                    'cost_at_argmin': float(cost[k])})
    return {'servo_rate_hz': servo_rate,
            'torque_limit_nm': None if torque_limit is None else np.asarray(
                torque_limit, dtype=float).tolist(),
            'cost_paper_gains': float(problem.cost(paper[None])[0]), 'gains': out}


def pd_study(generations, seeds, log, path, argv):
    """
    Run :data:`PD_STUDY` and :data:`PD_SCANS`, writing ``path`` after every row.

    Rows already in ``path`` (same servo rate, limit and seed) are kept and not run again.
    """
    peak = peak_torque(PlanarArm.paper(), paper_reference(3))
    study = {'rows': []}
    if os.path.exists(path):
        with open(path, encoding='utf-8') as f:
            study = json.load(f)
    study['meta'] = dict(study.get('meta', {}), **{
        'date': datetime.date.today().isoformat(),
        'command': 'python tools/paper.py ' + ' '.join(argv),
        'load_start': os.getloadavg(), 'generations': generations, 'population_size': 60,
        'peak_torque_nm': peak.tolist(),
        'reference': 'paper_reference(3), 10 s, error sampled at 100 Hz',
        'servo': 'digital: state read at the servo rate, torque held (zero-order hold) and '
                 'clipped to the limit; continuous: PD at every integration stage, no limit'})

    def write():
        study['meta']['load_end'] = os.getloadavg()
        with open(path, 'w', encoding='utf-8') as f:
            json.dump(_finite_or_none(study), f, indent=2)

    def limit_of(factor):
        return None if factor is None else (factor * peak).tolist()

    done = {(r['servo_rate_hz'], r['torque_limit_nm'] and tuple(r['torque_limit_nm']),
             r['seed']) for r in study['rows']}
    study['scans'] = [coordinate_scan(rate, limit_of(factor)) for rate, factor in PD_SCANS]
    write()
    for servo_rate, factor in PD_STUDY:
        limit = limit_of(factor)
        for seed in seeds:
            if (servo_rate, limit and tuple(limit), seed) in done:
                continue
            study['rows'].append(tune_gains(generations, log, servo_rate, limit, seed))
            write()
    return study


def _percent(value):
    """Format a fraction as a percentage; a diverged rollout (inf/NaN) says so."""
    return f'{100 * value:.3g}%' if np.isfinite(value) else 'diverged'


def _cost(value):
    """Format a cost; a diverged one (inf, or None in the JSON) says so."""
    return 'diverged' if value is None or not np.isfinite(value) else f'{value:.4g}'


def pd_table(rows):
    """Return markdown lines of the PD tuning rows (:func:`tune_gains` dicts)."""
    lines = ['| servo | torque limit [N m] | seed | Kp found | Kd found | J found | '
             "J of the paper's gains |", '|---|---|---|---|---|---|---|']
    for r in rows:
        servo = 'continuous' if r['servo_rate_hz'] is None else f"{r['servo_rate_hz']:g} Hz"
        limit = 'none' if r['torque_limit_nm'] is None else str(r['torque_limit_nm'])
        lines.append(f"| {servo} | {limit} | {r['seed']} | "
                     f"{np.round(r['kp_found'], 2).tolist()} | "
                     f"{np.round(r['kd_found'], 2).tolist()} | {_cost(r['cost_found'])} | "
                     f"{_cost(r['cost_paper_gains'])} |")
    return lines


def write_markdown(results, path, pd_rows=None):
    """Write the summary table (and the PD tuning study's, if it was run)."""
    meta = results['meta']
    lines = ['# Paper reproduction (`make paper`)', '',
             f"Generated {meta['date']} by `tools/paper.py` on {meta['machine']} (load "
             f"{meta['load_start'][0]:.1f} at start, {meta['load_end'][0]:.1f} at the end; "
             "our pipeline's wall-time budget makes its figures depend on the machine's "
             "speed); fitting data: 10 s of the paper's arm under its PD following "
             '`paper_reference`, 100 Hz; held-out: a 10 s open-loop rollout on '
             '`heldout_reference` (not used for fitting). θ-NRMSE = RMSE / std of the '
             'measured θ, averaged over joints. Start J: the cost of the genome each search '
             'starts from (the paper EA keeps it in its first generation; `diverged`: its '
             'rollout leaves the plausible range, J = ∞, `Infinity` in the JSON); for our '
             'pipeline the neutral genome of its structure, before the closed-form fit, and '
             'its J is on the older 80 % of the data it fits (the newest 20 % choose its '
             'stage).', '',
             f"The paper EA: {meta['paper_ea']}.", '',
             '| case | optimizer | genome | start J | final J (fit data) | held-out θ-NRMSE | '
             'fit θ-NRMSE | evaluations | wall [s] |',
             '|---|---|---|---|---|---|---|---|---|']
    for case in ('1', '2', '3'):
        if case not in results:
            continue
        for name in ('paper_ea', 'best'):
            r = results[case][name]
            lines.append(f"| {case} | {name} | {r['genome_size']} | {_cost(r['start_cost'])} | "
                         f"{_cost(r['final_cost'])} | {_percent(r['heldout_nrmse'])} | "
                         f"{_percent(r['fit_nrmse'])} | {r['evaluations']} | "
                         f"{r['wall_s']:.0f} |")
    pd = results.get('pd_tuning')
    if pd or pd_rows:
        lines += ['', '## PD gain tuning (eq. 10, the paper EA, 60 individuals × 200 '
                  'generations)', '', "The paper's gains: Kp = diag(32.84, 42.05, 42.31), "
                  'Kd = diag(42.44, 0.19, 4.86). Bounds Kp in [0, 100], Kd in [0, 50].', '']
        lines += pd_table(([pd] if pd else []) + list(pd_rows or []))
        if pd_rows:
            lines += ['', 'Rows after the first: `pd_tuning.json` (`tools/paper.py '
                      '--pd-study`), a digital servo (state read at the servo rate, torque '
                      'held and clipped to the limit).']
    lines += ['', 'Figures: `figures/case*_trajectories.png` (measured vs identified, like the '
              "paper's Figs. 9, 11, 13) and `figures/case*_evolution.png` (Figs. 10, 12, 14: "
              'best and mean J per generation, diverged individuals per generation; our '
              "pipeline's best so far with each stage marked).", '']
    with open(path, 'w', encoding='utf-8') as f:
        f.write('\n'.join(lines))


def _finite_or_none(value, key=None):
    """
    Strict JSON: a diverged (inf/NaN) number becomes null.

    Except a ``start_cost`` of +inf (a start genome whose rollout diverges), written as
    ``Infinity``: a search's final J is compared with it, and null would compare with nothing.
    """
    if key == 'start_cost' and isinstance(value, float) and value == np.inf:
        return value
    if isinstance(value, dict):
        return {k: _finite_or_none(v, k) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def main(argv=None):
    """Run the reproduction; return the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--cases', default='1,2,3')
    parser.add_argument('--generations', type=int, default=200,
                        help='paper EA generations (paper: 200)')
    parser.add_argument('--best-budget', type=float, default=120.0,
                        help='wall-time budget of our pipeline per case [s]')
    parser.add_argument('--tuning-generations', type=int, default=200)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--out', default=os.path.join(os.path.dirname(HERE), 'bench',
                                                      'results'))
    parser.add_argument('--spread-study', default='',
                        help='comma-separated initial spreads: run only the study of the '
                        "paper EA's initial spread and write paper_ea_spread.json")
    parser.add_argument('--study-seeds', default='0')
    parser.add_argument('--pd-study', action='store_true',
                        help='run only the PD tuning study and write pd_tuning.json')
    args = parser.parse_args(argv)

    def log(msg):
        print(msg, flush=True)

    out_dir = args.out
    fig_dir = os.path.join(out_dir, 'figures')
    os.makedirs(fig_dir, exist_ok=True)
    fit_data, held, kp, kd = make_data()
    if args.pd_study:
        pd_study(args.tuning_generations, [int(v) for v in args.study_seeds.split(',')], log,
                 os.path.join(out_dir, 'pd_tuning.json'), argv or sys.argv[1:])
        return 0
    if args.spread_study:
        spreads = [float(v) for v in args.spread_study.split(',')]
        seeds = [int(v) for v in args.study_seeds.split(',')]
        t0 = time.perf_counter()
        study = {'meta': {'date': datetime.date.today().isoformat(),
                          'command': 'python tools/paper.py ' + ' '.join(argv or sys.argv[1:]),
                          'load_start': os.getloadavg(), 'generations': args.generations}}
        study.update(spread_study([c.strip() for c in args.cases.split(',')], spreads, seeds,
                                  args.generations, fit_data, held, kp, kd, log))
        study['meta'].update(load_end=os.getloadavg(), wall_s=time.perf_counter() - t0)
        with open(os.path.join(out_dir, 'paper_ea_spread.json'), 'w', encoding='utf-8') as f:
            json.dump(_finite_or_none(study), f, indent=2)
        return 0
    results = {'meta': {'date': datetime.date.today().isoformat(),
                        'machine': f'{platform.machine()}, {os.cpu_count()} cpus',
                        'command': 'python tools/paper.py ' + ' '.join(argv or sys.argv[1:]),
                        'load_start': os.getloadavg(),
                        'seed': args.seed, 'generations': args.generations,
                        'best_budget_s': args.best_budget,
                        'paper_ea': paper_ea_description()}}
    for case in args.cases.split(','):
        case = case.strip()
        log(f'== {TITLES[case]}')
        runs = {'paper_ea': run_paper_ea(case, fit_data, kp, kd, args.generations, args.seed,
                                         log)}
        log(f'  case {case} ours: closed form, LM, CMA-ES, at most {args.best_budget:.0f} s')
        res = fit_best(fit_data, CASES[case], time_budget=args.best_budget, kp=kp, kd=kd,
                       seed=args.seed)
        runs['best'] = {'model': res.model, 'history': res.history, 'wall_s': res.wall_s,
                        'evaluations': res.evaluations, 'final_cost': res.final_cost,
                        'start_cost': res.history[0]['cost']}
        results[case] = {}
        for name, run in runs.items():
            m = run['model']
            entry = {'start_cost': float(run['start_cost']),
                     'final_cost': float(run['final_cost']),
                     'heldout_nrmse': nrmse(m.predict(held)[:, :3], held.theta),
                     'fit_nrmse': nrmse(m.predict(fit_data)[:, :3], fit_data.theta),
                     'evaluations': int(run['evaluations']), 'wall_s': float(run['wall_s']),
                     'genome_size': int(m.spec.genome_size), 'network': m.spec.to_dict(),
                     'history': compact_history(name, run['history'])}
            gains = m.implied_gains()
            if gains is not None:
                entry['implied_kp'] = np.asarray(gains[0]).tolist()
                entry['implied_kd'] = np.asarray(gains[1]).tolist()
            results[case][name] = entry
            log(f"  case {case} {name:8s}: start J {entry['start_cost']:.4g}  J "
                f"{entry['final_cost']:.4g}  held-out θ-NRMSE "
                f"{entry['heldout_nrmse']:.2%}  fit θ-NRMSE {entry['fit_nrmse']:.2%}  "
                f"{entry['evaluations']} evaluations  {entry['wall_s']:.0f} s")
        for path in plot_case(case, fit_data, held, runs, fig_dir):
            log(f'  wrote {os.path.relpath(path)}')
    results['pd_tuning'] = tune_gains(args.tuning_generations, log)
    results['meta']['load_end'] = os.getloadavg()
    with open(os.path.join(out_dir, 'paper.json'), 'w', encoding='utf-8') as f:
        json.dump(_finite_or_none(results), f, indent=2)
    pd_rows = None
    if os.path.exists(os.path.join(out_dir, 'pd_tuning.json')):
        with open(os.path.join(out_dir, 'pd_tuning.json'), encoding='utf-8') as f:
            pd_rows = json.load(f)['rows']
    write_markdown(results, os.path.join(out_dir, 'paper.md'), pd_rows)
    log(f"wrote {os.path.relpath(os.path.join(out_dir, 'paper.json'))} and paper.md")
    return 0


if __name__ == '__main__':
    sys.exit(main())
