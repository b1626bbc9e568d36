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
- ``best``: our structure (``NetworkSpec.recommended``) and pipeline (``fit_best``:
  Levenberg-Marquardt on multiple-shooting residuals, then CMA-ES) in a wall-time budget.

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


def run_paper_ea(case, fit_data, kp, kd, generations, seed, log):
    """Return (model, history, wall_s) of the paper's structure and EA."""
    spec = NetworkSpec.paper(3, CASES[case])
    evo = Evolution(spec, fit_data, 'paper', {'population_size': 100}, seed, kp, kd,
                    torque_interpolation='hold')
    history = []
    t0 = time.perf_counter()
    for _ in range(generations):
        stats = evo.step()
        stats['wall_s'] = time.perf_counter() - t0
        history.append(stats)
        if stats['generation'] % 20 == 0 or stats['generation'] == 1:
            log(f"  case {case} paper EA  gen {stats['generation']:4d}  "
                f"best J {stats['best_cost']:.4g}  mean J {stats['mean_cost']:.4g}  "
                f"spread {stats['spread']:.3g}  {stats['wall_s']:.0f} s")
    return evo.best_model(fit_data.joint_names), history, time.perf_counter() - t0


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

    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    hist = runs['paper_ea']['history']
    gens = [h['generation'] for h in hist]
    axes[0].semilogy(gens, [h['best_cost'] for h in hist], 'C1', label='best')
    axes[0].semilogy(gens, [h['mean_cost'] for h in hist], 'C1', alpha=0.4,
                     label='mean (finite)')
    axes[0].set_title(f'{TITLES[case]}: paper EA')
    axes[0].set_xlabel('generation')
    axes[0].set_ylabel('J')
    axes[0].legend()
    hist = [h for h in runs['best']['history'] if h.get('phase') == 'cmaes']
    if hist:
        axes[1].semilogy([h['wall_s'] for h in hist], [h['best_cost'] for h in hist], 'C0',
                         label='best')
        axes[1].semilogy([h['wall_s'] for h in hist], [h['mean_cost'] for h in hist], 'C0',
                         alpha=0.4, label='mean (finite)')
    axes[1].set_title(f'{TITLES[case]}: LM + CMA-ES (CMA-ES phase)')
    axes[1].set_xlabel('wall time [s]')
    axes[1].set_ylabel('J')
    axes[1].legend()
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    path = os.path.join(out_dir, f'case{case}_evolution.png')
    fig.savefig(path, dpi=90)
    plt.close(fig)
    paths.append(path)
    return paths


def tune_gains(generations, log):
    """Run the paper's PD tuning (eq. 10) if the tuning module exists; return a dict."""
    try:
        from rkgnn_ros.core.sim.tuning import tune_pd_gains
    except ImportError:
        log('  PD tuning: rkgnn_ros.core.sim.tuning is not available, skipped')
        return None
    arm = PlanarArm.paper()
    result = tune_pd_gains(arm, paper_reference(3), duration=10.0, population_size=60,
                           generations=generations, seed=0)
    out = {'kp_found': np.asarray(result.kp).tolist(), 'kd_found': np.asarray(result.kd).tolist(),
           'cost_found': float(result.cost),
           'kp_paper': [32.84, 42.05, 42.31], 'kd_paper': [42.44, 0.19, 4.86],
           'cost_paper_gains': float(getattr(result, 'paper_cost', float('nan'))),
           'evaluations': int(getattr(result, 'evaluations', 0)),
           'wall_s': float(getattr(result, 'wall_s', 0.0))}
    log(f"  PD tuning: Kp {np.round(out['kp_found'], 2)} Kd {np.round(out['kd_found'], 2)} "
        f"cost {out['cost_found']:.4g} (paper's gains: {out['cost_paper_gains']:.4g})")
    return out


def _percent(value):
    """Format a fraction as a percentage; a diverged rollout (inf/NaN) says so."""
    return f'{value:.2%}' if np.isfinite(value) else 'diverged'


def write_markdown(results, path):
    """Write the summary table."""
    lines = ['# Paper reproduction (`make paper`)', '',
             f"Generated {results['meta']['date']} by `tools/paper.py` on "
             f"{results['meta']['machine']}; fitting data: 10 s of the paper's arm under its "
             'PD following `paper_reference`, 100 Hz; held-out: a 10 s open-loop rollout on '
             '`heldout_reference` (not used for fitting). θ-NRMSE = RMSE / std of the '
             'measured θ, averaged over joints.', '',
             '| case | optimizer | genome | final J (fit data) | held-out θ-NRMSE | '
             'fit θ-NRMSE | evaluations | wall [s] |',
             '|---|---|---|---|---|---|---|---|']
    for case in ('1', '2', '3'):
        if case not in results:
            continue
        for name in ('paper_ea', 'best'):
            r = results[case][name]
            lines.append(f"| {case} | {name} | {r['genome_size']} | {r['final_cost']:.4g} | "
                         f"{_percent(r['heldout_nrmse'])} | {_percent(r['fit_nrmse'])} | "
                         f"{r['evaluations']} | {r['wall_s']:.0f} |")
    pd = results.get('pd_tuning')
    if pd:
        lines += ['', '## PD gain tuning (eq. 10, the same EA, 60 individuals × 200 generations)',
                  '', '| | Kp | Kd | tracking cost (eq. 10) |', '|---|---|---|---|',
                  f"| paper | {pd['kp_paper']} | {pd['kd_paper']} | "
                  f"{pd['cost_paper_gains']:.4g} |",
                  f"| ours | {np.round(pd['kp_found'], 2).tolist()} | "
                  f"{np.round(pd['kd_found'], 2).tolist()} | {pd['cost_found']:.4g} |"]
    lines += ['', 'Figures: `figures/case*_trajectories.png` (measured vs identified, like the '
              "paper's Figs. 9, 11, 13) and `figures/case*_evolution.png` (Figs. 10, 12, 14).",
              '']
    with open(path, 'w', encoding='utf-8') as f:
        f.write('\n'.join(lines))


def _finite_or_none(value):
    """Strict JSON: a diverged (inf/NaN) number becomes null."""
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
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
    args = parser.parse_args(argv)

    def log(msg):
        print(msg, flush=True)

    out_dir = args.out
    fig_dir = os.path.join(out_dir, 'figures')
    os.makedirs(fig_dir, exist_ok=True)
    fit_data, held, kp, kd = make_data()
    results = {'meta': {'date': datetime.date.today().isoformat(),
                        'machine': f'{platform.machine()}, {os.cpu_count()} cpus',
                        'seed': args.seed, 'generations': args.generations,
                        'best_budget_s': args.best_budget}}
    for case in args.cases.split(','):
        case = case.strip()
        log(f'== {TITLES[case]}')
        runs = {}
        model, history, wall = run_paper_ea(case, fit_data, kp, kd, args.generations,
                                            args.seed, log)
        runs['paper_ea'] = {'model': model, 'history': history, 'wall_s': wall,
                            'evaluations': history[-1]['evaluations'],
                            'final_cost': history[-1]['best_cost']}
        log(f'  case {case} ours: LM + CMA-ES for {args.best_budget:.0f} s')
        res = fit_best(fit_data, CASES[case], args.best_budget, kp=kp, kd=kd, seed=args.seed)
        runs['best'] = {'model': res.model, 'history': res.history, 'wall_s': res.wall_s,
                        'evaluations': res.evaluations, 'final_cost': res.final_cost}
        results[case] = {}
        for name, run in runs.items():
            m = run['model']
            entry = {'final_cost': float(run['final_cost']),
                     'heldout_nrmse': nrmse(m.predict(held)[:, :3], held.theta),
                     'fit_nrmse': nrmse(m.predict(fit_data)[:, :3], fit_data.theta),
                     'evaluations': int(run['evaluations']), 'wall_s': float(run['wall_s']),
                     'genome_size': int(m.spec.genome_size), 'network': m.spec.to_dict()}
            gains = m.implied_gains()
            if gains is not None:
                entry['implied_kp'] = np.asarray(gains[0]).tolist()
                entry['implied_kd'] = np.asarray(gains[1]).tolist()
            results[case][name] = entry
            log(f"  case {case} {name:8s}: J {entry['final_cost']:.4g}  held-out θ-NRMSE "
                f"{entry['heldout_nrmse']:.2%}  fit θ-NRMSE {entry['fit_nrmse']:.2%}  "
                f"{entry['evaluations']} evaluations  {entry['wall_s']:.0f} s")
        for path in plot_case(case, fit_data, held, runs, fig_dir):
            log(f'  wrote {os.path.relpath(path)}')
    results['pd_tuning'] = tune_gains(args.tuning_generations, log)
    with open(os.path.join(out_dir, 'paper.json'), 'w', encoding='utf-8') as f:
        json.dump(_finite_or_none(results), f, indent=2)
    write_markdown(results, os.path.join(out_dir, 'paper.md'))
    log(f"wrote {os.path.relpath(os.path.join(out_dir, 'paper.json'))} and paper.md")
    return 0


if __name__ == '__main__':
    sys.exit(main())
