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
Render ``bench/results/README.md`` from the JSON every benchmark writes.

Run by ``bench/run_all.py`` after the benchmarks (``make bench``), or alone:
``python bench/summary.py``. Sections for missing files are left out; nothing is typed in
by hand.
"""

import json
import math
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, 'results')
METHODS = ('true_model', 'rkgnn_paper_ea', 'rkgnn_best', 'rkgnn_best_2min', 'rkgnn_trig',
           'pysindy', 'least_squares', 'unstructured_rbf', 'hold_last', 'follow_reference')


def _load(name):
    path = os.path.join(RESULTS, f'{name}.json')
    if not os.path.exists(path):
        return None
    with open(path, encoding='utf-8') as f:
        return json.load(f)


def _pct(value):
    return '–' if value is None else f'{100 * value:.2f} %'


def _cell(entry, key):
    if entry is None:
        return '–'
    if entry.get('diverged'):
        return 'diverged'
    if entry.get(key) is None:
        return 'n/a' if entry.get('cannot') or entry.get('skipped') else '–'
    return _pct(entry[key])


def peers_section(d):
    lines = ['## Accuracy against peers (`bench/peers.py`)', '',
             f"{d['meta']['metric']}. Held-out runs: {', '.join(d['meta']['heldout'])}. "
             f"Evaluation budget {d['meta']['evaluation_budget']}, wall-time budget "
             f"{d['meta']['wall_budget_s']:.0f} s, {d['meta']['wall_s']:.0f} s in all "
             f"(load {d['meta']['load_start'][0]:.1f} at start).", '']
    for key, data in (('clean_only_run', 'noiseless'), ('noisy_only_run', 'noisy')):
        extra = d['meta'].get(key)
        if extra:
            methods = ', '.join(m for m in extra['methods'] if m != 'true_model')
            flag = '--' + key[:-len('_run')].replace('_', '-')
            lines[-1:-1] = [f'The {data} figures of {methods} come from a later `{flag}` run '
                            f"of the same script on the same data ({extra['wall_s']:.0f} s, "
                            f"{extra['date']}, load {extra['load_start'][0]:.1f} at start)."]
    for title, block, key in (('10 s open loop, no noise', d, 'heldout_nrmse_10s'),
                              ('2 s ahead, no noise', d, 'ahead_nrmse_2s'),
                              ('10 s open loop, encoder noise', d.get('noisy', {}),
                               'heldout_nrmse_10s'),
                              ('Held-out torque NRMSE (inverse dynamics), no noise', d,
                               'torque_nrmse'),
                              ('Held-out torque NRMSE, encoder noise', d.get('noisy', {}),
                               'torque_nrmse')):
        cases = [c for c in ('1', '2', '3') if c in block]
        if not cases:
            continue
        lines += [f'### {title}', '', '| method | ' + ' | '.join(f'case {c}' for c in cases)
                  + ' |', '|---|' + '---|' * len(cases)]
        for method in METHODS:
            if key == 'torque_nrmse' and not any(
                    (block[c].get(method) or {}).get(key) is not None for c in cases):
                continue  # a method without an inverse dynamics
            lines.append(f'| {method} | ' + ' | '.join(_cell(block[c].get(method), key)
                                                       for c in cases) + ' |')
        lines.append('')
    lines += ['`n/a`: the method cannot do that case (least squares needs the measured '
              'torque) or was not run on noisy data (time); `diverged`: its rollout '
              'overflowed. Torque NRMSE: RMSE / std of the applied torque of M θ̈ + V + G + F '
              "on the held-out runs' measured states (θ̈ by Savitzky-Golay); case 3 after the "
              'scale is fixed by the true mean Kp.', '']
    return lines


def _cost(value):
    return 'diverged' if value is None or not math.isfinite(value) else f'{value:.4g}'


def _held(entry):
    return 'diverged' if entry['heldout_nrmse'] is None else _pct(entry['heldout_nrmse'])


def paper_section(d):
    """Return the lines of the paper's structure and EA beside our pipeline (paper.json)."""
    meta = d['meta']
    load = (f", load {meta['load_start'][0]:.1f} at start and {meta['load_end'][0]:.1f} at "
            'the end' if 'load_end' in meta else '')
    lines = ['## Paper reproduction (`tools/paper.py`, `make paper`)', '',
             f"{meta['date']}{load}. J on the 10 s fitting run (start: the genome the search "
             'starts from), and the 10 s open-loop θ-NRMSE on the held-out reference. '
             f"Ours: `fit_best` with {meta['best_budget_s']:.0f} s of wall time (its figures "
             "depend on the machine's speed). Details and figures: `paper.md`.", '',
             '| case | paper EA start J | paper EA final J | paper EA held-out | '
             'ours start J | ours final J | ours held-out |', '|---|---|---|---|---|---|---|']
    for case in ('1', '2', '3'):
        if case in d:
            p, b = d[case]['paper_ea'], d[case]['best']
            lines.append(f"| {case} | {_cost(p.get('start_cost'))} | {_cost(p['final_cost'])} "
                         f"| {_held(p)} | {_cost(b.get('start_cost'))} | "
                         f"{_cost(b['final_cost'])} | {_held(b)} |")
    return lines + ['']


def spread_section(d):
    """Return the lines of the paper EA's final J per initial spread (paper_ea_spread.json)."""
    cases = [c for c in ('1', '2', '3') if c in d]
    spreads = list(d[cases[0]]) if cases else []
    lines = ["## The paper EA's initial spread (`tools/paper.py --spread-study`)", '',
             f"J after {d['meta']['generations']} generations of 100, the start genome in the "
             'first generation and the rest around it at the spread, which is also where the '
             'mutation spread starts (per seed; `paper_ea_spread.json`, '
             f"`{d['meta']['command']}`, load {d['meta']['load_start'][0]:.1f} at start).", '',
             '| spread | ' + ' | '.join(f'case {c}' for c in cases) + ' |',
             '|---|' + '---|' * len(cases)]
    for spread in spreads:
        lines.append(f'| {spread} | ' + ' | '.join(
            ' / '.join(_cost(r['final_cost']) for r in d[c][spread]) for c in cases) + ' |')
    return lines + ['']


def _servo_order(row):
    """Sort key: continuous first, then faster servos, then looser torque limits."""
    rate = row['servo_rate_hz']
    limit = row['torque_limit_nm']
    return (-(float('inf') if rate is None else rate),
            -(float('inf') if limit is None else sum(limit)))


def pd_tuning_section(d):
    """Return the lines of the PD tuning study (pd_tuning.json)."""
    lines = ['## PD tuning, eq. (10) (`tools/paper.py --pd-study`)', '',
             f"The paper EA, {d['meta']['population_size']} individuals × "
             f"{d['meta']['generations']} generations; {d['meta']['servo']}. The paper's "
             'gains: Kp = diag(32.84, 42.05, 42.31), Kd = diag(42.44, 0.19, 4.86).', '',
             '| servo | torque limit [N m] | Kp found | Kd found | J found | '
             "J of the paper's gains |", '|---|---|---|---|---|---|']
    for r in sorted(d['rows'], key=_servo_order):
        servo = 'continuous' if r['servo_rate_hz'] is None else f"{r['servo_rate_hz']:g} Hz"
        limit = 'none' if r['torque_limit_nm'] is None else str(r['torque_limit_nm'])
        lines.append(f"| {servo} | {limit} | {[round(v, 2) for v in r['kp_found']]} | "
                     f"{[round(v, 2) for v in r['kd_found']]} | {_cost(r['cost_found'])} | "
                     f"{_cost(r['cost_paper_gains'])} |")
    scans = d.get('scans')
    if scans:
        names = [g['gain'] for g in scans[0]['gains']]
        lines += ['', 'Each gain swept over its bounds (41 values) with the others at the '
                  "paper's: where J is lowest (the paper's value in the header).", '',
                  '| servo | torque limit [N m] | ' + ' | '.join(
                      f"{g['gain']} ({g['paper']:g})" for g in scans[0]['gains'])
                  + " | J of the paper's gains |", '|---|---|' + '---|' * (len(names) + 1)]
        for scan in sorted(scans, key=_servo_order):
            servo = ('continuous' if scan['servo_rate_hz'] is None
                     else f"{scan['servo_rate_hz']:g} Hz")
            limit = 'none' if scan['torque_limit_nm'] is None else str(scan['torque_limit_nm'])
            lines.append(f'| {servo} | {limit} | ' + ' | '.join(
                f"{g['argmin']:g}" if g['cost_at_argmin'] is not None else 'all diverge'
                for g in scan['gains']) + f" | {_cost(scan['cost_paper_gains'])} |")
    return lines + ['']


def generalization_section(d):
    """Return the generalization table: per arm, case and noise, ours beside the true model."""
    meta = d.get('meta', {})
    out = ['## Beyond the training motion (`bench/generalization.py`)', '',
           f"Planar arms fitted on {meta.get('fit_s', '?')} s of one reference and scored on "
           'a reference around another pose. Ours: ' + str(meta.get('ours', '?')) + '. '
           'θ: 10 s held-out rollout NRMSE; τ: inverse-dynamics torque NRMSE on the held-out '
           'states. Noisy: ' + str(meta.get('noise', '?')) + '.', '',
           '| links | case | θ ours | θ true model | τ ours | τ true model | '
           'θ ours, noisy | τ ours, noisy |', '|---|---|---|---|---|---|---|---|']
    noisy = d.get('noisy', {})
    for n in meta.get('arms', sorted(k for k in d if k.isdigit())):
        for case in ('1', '2', '3'):
            entry = d.get(n, {}).get(case)
            if not entry:
                continue
            true = entry.get('methods', {}).get('true_model', {})
            loud = noisy.get(n, {}).get(case, {})
            out.append(f'| {n} | {case} | {_pct(entry.get("heldout_nrmse_10s"))} | '
                       f'{_pct(true.get("heldout_nrmse_10s"))} | '
                       f'{_pct(entry.get("torque_nrmse"))} | {_pct(true.get("torque_nrmse"))} | '
                       f'{_pct(loud.get("heldout_nrmse_10s"))} | '
                       f'{_pct(loud.get("torque_nrmse"))} |')
    out.append('')
    return out


def _mean_rate(soak):
    rates = [float(s['generations_per_s']) for s in soak['samples']
             if s.get('generations_per_s') not in (None, '')]
    return sum(rates) / len(rates) if rates else float('nan')


def _ratio(value) -> str:
    """Return a ratio with three decimals, '–' when missing."""
    return '–' if value is None else f'{value:.3f}'


def _num(value, fmt='{:.3g}'):
    return '–' if value is None else fmt.format(value)


def urdf_arms_section(d):
    """Return the lines of ``urdf_arms.json`` (arm x servo x sensors, and the perturbed URDF)."""
    lines = ['## Arms with a robot description (`bench/urdf_arms.py`)', '',
             '2 s-ahead θ error at 60 s (share of the θ range) of what `~/prediction` '
             'published, against following the reference; seconds from the first '
             'joint_states to the first model prediction; held-out torque NRMSE (case 1).', '']
    for title, table in (('exact URDF', d), ('URDF inertials scaled by [0.7, 1.3], no friction',
                                             d.get('perturbed_urdf') or {})):
        cells = [(arm, servo, sensors, cell) for arm, servos in table.items()
                 if isinstance(servos, dict) and arm in ('ur5', 'panda')
                 for servo, sensors_ in servos.items() for sensors, cell in sensors_.items()]
        if not cells:
            continue
        lines += [f'### {title}', '', '| arm | servo | sensors | prediction | follow reference '
                  '| ratio | first model (s) | torque NRMSE | worst joint / baseline |',
                  '|---|---|---|---|---|---|---|---|---|']
        for arm, servo, sensors, c in cells:
            if 'error' in c:
                lines.append(f'| {arm} | {servo} | {sensors} | {c["error"]} | | | | | |')
                continue
            p, f = c.get('prediction_nrmse_60s'), c.get('follow_reference_nrmse')
            ratio = p / f if p is not None and f else None
            lines.append(f'| {arm} | {servo} | {sensors} | {_pct(p)} | {_pct(f)} | '
                         f'{_num(ratio)} | {_num(c.get("first_model_prediction_s"), "{:.1f}")}'
                         f' | {_pct(c.get("torque_nrmse"))} | '
                         f'{_num(c.get("self_check_worst_joint_ratio"))} |')
        lines += ['', f'Worst ratio {_num(table.get("worst_ratio_to_follow_reference"))}, '
                      f'worst first model {_num(table.get("worst_first_model_prediction_s"))} '
                      f's, worst torque NRMSE {_pct(table.get("worst_torque_nrmse"))}.', '']
    return lines


def real_panda_section(d):
    """Return the lines of ``real_panda.json``."""
    per_joint = ', '.join(f'{v:.4f}' for v in d['nmse_per_joint'])
    return ['## The real Panda (`bench/real_panda.py`)', '',
            f"Held-out torque nMSE (last 30 % of the recording): mean {d['nmse_mean']:.4f} "
            f"(joints {per_joint}); the published model file {d['published_nmse_mean']:.4f}; "
            f"least squares on the URDF regressor {d['least_squares_nmse_mean']:.4f}; "
            f"fit {d['fit_s']:.2f} s; physically consistent: {d['consistent']}.", '']


def change_section(d):
    """Return the lines of ``change.json``."""
    lines = ['## A payload picked up and released (`bench/change.py`)', '',
             '| arm | sensors | event | error before | worst after | recovery (s) | '
             'detection (s) | mass error | com error (m) |',
             '|---|---|---|---|---|---|---|---|---|']
    for arm in ('paper', 'ur5'):
        for sensors, cell in (d.get(arm) or {}).items():
            for event in ('attach', 'detach'):
                e = cell.get(event) if isinstance(cell, dict) else None
                if not e:
                    continue
                lines.append(f"| {arm} | {sensors} | {event} | {_pct(e.get('error_before'))} | "
                             f"{_pct(e.get('error_after_peak'))} | {_num(e.get('recovery_s'))} | "
                             f"{_num(e.get('detection_delay_s'))} | "
                             f"{_num(e.get('payload_mass_error'))} | "
                             f"{_num(e.get('payload_com_error_m'))} |")
    lines += ['', 'Worst recovery: with a robot description '
                  f"{_num(d.get('worst_recovery_s_urdf'))}"
                  f" s, without {_num(d.get('worst_recovery_s_no_urdf'))} s; changes said in "
                  f"10 minutes without one: {d.get('false_alarms_10min', '–')}. What was "
                  'published against the better baseline, worst 10 s window of 2 s-ahead '
                  f"errors: {_ratio(d.get('self_check_worst_ratio'))} over the joints, "
                  f"{_ratio(d.get('self_check_worst_joint_ratio'))} on the worst joint.", '']
    return lines


def reliability_lines(budgets, hostile):
    """Return the lines of ``budgets.json`` and ``hostile.json``."""
    lines = []
    if hostile:
        lines += ['## Hostile input (`bench/hostile.py`)', '',
                  f"{hostile['breaks_survived']} of {hostile['breaks_tested']} breaks refused "
                  f"and survived, {hostile['tracebacks']} tracebacks, "
                  f"{hostile.get('drop_burst_tracebacks')} in the 1 kHz drop-and-burst run; "
                  f"largest identifier RSS {hostile['max_rss_mb']} MB.", '']
    if budgets:
        lines += ['## Time budgets (`bench/budgets.py`)', '', '| entry point | budget | alone (s) '
                  '| loaded (s) |', '|---|---|---|---|']
        for entry, per_budget in budgets['cells'].items():
            for budget, loads in per_budget.items():
                lines.append(f'| {entry} | {budget} | '
                             f"{_num((loads.get('alone') or {}).get('wall_s'), '{:.2f}')} | "
                             f"{_num((loads.get('loaded') or {}).get('wall_s'), '{:.2f}')} |")
        lines += ['', f"Worst wall time over budget: {_num(budgets['worst_overrun_ratio'])}.", '']
    return lines


def rigid_speed_lines(speed, latency):
    """Return the lines of ``rigid_speed.json`` and the Panda at 1 kHz of ``latency.json``."""
    lines = []
    if speed:
        lines += ['## The rigid body at 7 joints (`bench/rigid_speed.py`)', '',
                  f"{speed['arm']}: closed form (law and arm, case 1) "
                  f"{speed['closed_form_s']:.2f} "
                  f"s, case 3 {speed['case3_s']:.2f} s (choosing its form "
                  f"{speed['case3_forms_s']:.2f} s), a 2 s prediction "
                  f"{speed['prediction_2s_ms']:.2f} ms.", '']
    panda = (latency or {}).get('panda_1khz')
    if panda:
        lines += [f"Panda at {panda['rate_hz']:.0f} Hz joint_states (`bench/latency.py --arm "
                  f"panda`): {panda['drops']} drops, state-to-prediction latency p99 "
                  f"{panda['latency_p99_ms']:.1f} ms (worst of {panda['runs_count']} runs).", '']
    return lines


def main():
    """Write bench/results/README.md."""
    out = ['# Benchmark results', '',
           'Generated by `bench/summary.py` from the JSON files in this folder '
           '(`make bench`; `make soak` and `make killtest` for the fault runs). Measured on '
           'a 2-core machine.', '']
    peers = _load('peers')
    if peers:
        out += peers_section(peers)
    generalization = _load('generalization')
    if generalization:
        out += generalization_section(generalization)
    speed = _load('fitness_speed')
    if speed:
        out += ['## Fitness speed (`bench/fitness_speed.py`)', '',
                f"Compiled kernel vs per-individual Python loop: {speed['speedup_vs_loop']:.0f}x; "
                f"vs batched numpy: {speed['speedup_vs_numpy']:.1f}x; evaluations per second: "
                + ', '.join(f'{k} {v:.0f}' for k, v in speed['evaluations_per_second'].items())
                + '.', '']
    online = _load('online')
    if online:
        out += ['## Online prediction (`bench/online.py`)', '',
                '2 s-ahead θ RMSE 60 s after start, as a share of the θ range: '
                + ', '.join(f"case {c} {_pct(online[c]['prediction_nrmse_60s'])}"
                            for c in ('1', '2', '3') if c in online) + '.', '']
    latency = _load('latency')
    if latency:
        out += ['## Responsiveness (`bench/latency.py`)', '',
                f"joint_states at {latency['rate_hz']:.0f} Hz while evolving: "
                f"{latency['drops_1khz']} drops, "
                f"{latency['generations_during_run']:.0f} generations per run; "
                f'state-to-prediction latency p50 '
                f"{latency['latency_p50_ms']:.1f} ms, p99 {latency['latency_p99_ms']:.1f} ms "
                f"(node's own: p50 {latency.get('node_latency_p50_ms')} ms, p99 "
                f"{latency.get('node_latency_p99_ms')} ms)"
                + (f"; worst of {latency['runs_count']} runs of {latency['duration_s']:.0f} s, "
                   f"p99 per run {[round(r['latency_p99_ms'], 1) for r in latency['runs']]} "
                   'ms' if latency.get('runs') else '') + '.', '']
    scaling = _load('scaling')
    if scaling:
        out += ['## Scale (`bench/scaling.py`)', '',
                'Seconds per generation (one population fitness), one factor varied at a '
                'time around 3 joints, 1000 samples, population 100:', '']
        for name in ('joints', 'window_samples', 'population'):
            entry = scaling[name]
            sizes = ', '.join(f'{v}: {s:.3f} s' for v, s in
                              zip(entry['values'], entry['seconds_per_generation']))
            out.append(f'- {name}: {sizes}; growth exponent '
                       f"{entry['growth_exponent']:.2f}")
        out += ['', 'Where the exponents come from: every individual integrates every '
                'sample, so the cost is linear in the population and in the window. Per '
                'RKG stage a model solves an n x n system and, with V from the Christoffel '
                'symbols, differentiates M (n^2 (n + 1) / 2 terms), which tends to n^3; at '
                '2-6 joints the RBF outputs (about n^2) and the per-step overhead still '
                'weigh, so the measured exponent is below 3.', '']
    evals = _load('evals_to_paper_cost')
    if evals:
        out += ["## Evaluations to reach the paper EA's final cost "
                '(`bench/evals_to_paper_cost.py`)', '',
                '| case | paper EA final J | paper EA evaluations | CMA-ES | '
                'equation error + CMA-ES |', '|---|---|---|---|---|']
        for case in ('1', '2', '3'):
            e = evals.get(case)
            if e:
                def _n(v):
                    return f'not within {e["cap"]}' if v is None else str(v)
                cost = e['paper_ea_final_cost']
                out.append(f"| {case} | {'diverged' if cost is None else f'{cost:.4g}'} | "
                           f"{e['paper_ea_evaluations']} | {_n(e.get('cmaes'))} | "
                           f"{_n(e.get('equation_error_then_cmaes'))} |")
        out.append('')
    soak = _load('soak')
    if soak:
        out += ['## Soak (`bench/soak.py`)', '',
                f"{soak['minutes']:.0f} min at 100 Hz with {soak['parameter_changes']} parameter "
                f"changes and {len(soak['resets'])} resets, "
                f'{_mean_rate(soak):.2f} generations/s: RSS growth minute 5 to end '
                f"{_pct(soak['rss_growth_fraction'])}, threads {soak['thread_count_start']} -> "
                f"{soak['thread_count_end']}, drops {soak['drops']}.", '']
    kill = _load('killtest')
    if kill:
        out += ['## SIGKILL during saves (`bench/killtest.py`)', '',
                f"{kill['kills']} kills: {kill['loadable']} model files loadable, "
                f"{kill['old_or_new']} the old or a new model.", '']
    paper = _load('paper')
    if paper:
        out += paper_section(paper)
    spread = _load('paper_ea_spread')
    if spread:
        out += spread_section(spread)
    tuning = _load('pd_tuning')
    if tuning:
        out += pd_tuning_section(tuning)
    for name, section in (('urdf_arms', urdf_arms_section), ('real_panda', real_panda_section),
                          ('change', change_section)):
        data = _load(name)
        if data:
            out += section(data)
    out += rigid_speed_lines(_load('rigid_speed'), _load('latency'))
    out += reliability_lines(_load('budgets'), _load('hostile'))
    text = '\n'.join(out)
    with open(os.path.join(RESULTS, 'README.md'), 'w', encoding='utf-8') as f:
        f.write(text)
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
