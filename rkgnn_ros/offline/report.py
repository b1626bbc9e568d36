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
What ``identify_bag`` writes besides the model: its figures and its report in Markdown.

:func:`write_figures` draws the held-out prediction beside the measured motion (and the
online model's, when the recording has one), the search's history and the coverage of the
joints; :func:`markdown` renders the report's dictionary (``report.json``'s content) for a
reader, a warning first when the model predicts the held-out part worse than a baseline.
"""

import math
import os
from typing import List

import numpy as np

__all__ = ['markdown', 'write_figures']


def write_figures(out: str, joints, heldout, predicted, online_predicted, history, train,
                  validation) -> List[str]:
    """Write the three figures; return their file names ([] without matplotlib)."""
    try:
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    n = len(joints)
    written = []
    if heldout and predicted:
        fig, axes = plt.subplots(n, 1, figsize=(9, 1.8 * n + 0.6), sharex=True, squeeze=False)
        for j, ax in enumerate(axes[:, 0]):
            for k, seg in enumerate(heldout):
                ax.plot(seg.t, seg.theta[:, j], 'k', lw=1.2, label='measured' if k == 0 else None)
                ax.plot(seg.t, predicted[k][:, j], 'C0--', lw=1.0,
                        label='identify_bag' if k == 0 else None)
                if online_predicted:
                    ax.plot(seg.t, online_predicted[k][:, j], 'C1:', lw=1.0,
                            label='online identifier' if k == 0 else None)
            ax.set_ylabel(f'{joints[j]}\n[rad]', fontsize=7)
        axes[0, 0].legend(fontsize=7, loc='upper right')
        axes[-1, 0].set_xlabel('t [s], held-out part')
        fig.suptitle('held-out part: measured vs predicted θ from its first state')
        fig.tight_layout()
        fig.savefig(os.path.join(out, 'heldout.png'), dpi=90)
        plt.close(fig)
        written.append('heldout.png')
    if history:
        rows = np.array([[h.generation, h.best_cost, h.validation_nrmse] for h in history])
        fig, ax = plt.subplots(figsize=(7, 3.2))
        ax.semilogy(rows[:, 0], rows[:, 1], label='best cost J')
        finite = np.isfinite(rows[:, 2])
        if finite.any():
            ax.semilogy(rows[finite, 0], rows[finite, 2], label='validation θ-NRMSE')
        ax.set_xlabel('generation')
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(os.path.join(out, 'evolution.png'), dpi=90)
        plt.close(fig)
        written.append('evolution.png')
    if train:
        fig, axes = plt.subplots(1, n, figsize=(2.2 * n + 1, 2.6), squeeze=False)
        parts = (('training', train), ('held out', heldout or []))
        for j, ax in enumerate(axes[0]):
            for label, segs in parts:
                if segs:
                    values = np.concatenate([seg.theta[:, j] for seg in segs])
                    still = np.ptp(values) <= 1e-9 * max(1.0, float(np.abs(values).max()))
                    ax.hist(values, bins=1 if still else 30, alpha=0.6, label=label)
            ax.set_title(joints[j], fontsize=7)
            ax.set_xlabel('θ [rad]', fontsize=7)
        axes[0, 0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(os.path.join(out, 'coverage.png'), dpi=90)
        plt.close(fig)
        written.append('coverage.png')
    return written


def markdown(report: dict) -> str:
    fit, data = report['fit'], report['data']
    lines = [f'# identify_bag: {report["recording"]}', '',
             f'- storage: {report["storage"]}; topics: {report["topics"]}',
             f'- joints: {report["joints"]}; case: {report["case"]}',
             f'- read: {data["messages"]}'
             + (f'; **{data["truncated"]}**' if data['truncated'] else ''),
             f'- drops (the node\'s rules): {data["drops"] or "none"}',
             f'- training: {data["training"]["seconds"]:.1f} s in '
             f'{data["training"]["segments"]} segment(s); held out: '
             f'{data["heldout"]["seconds"]:.1f} s', '',
             '## Fit', '',
             f'- {fit["generations"]} generations in {fit["seconds"]:.1f} s '
             f'(budget {fit["budget_s"]:g} s), final state {fit["state"]!r}',
             f'- best cost J {fit["cost"]:.4g}, validation θ-NRMSE (newest '
             f'{report["validation_fraction"]:.0%} of the training part) '
             f'{fit["validation_nrmse"]:.4g}',
             '', '## Held out', '',
             f'- identify_bag\'s model: θ-NRMSE {report["heldout"]["nrmse"]:.4g} '
             f'({report["heldout"]["how"]})']
    lines += [f'- {name.replace("_", " ")} (no model): θ-NRMSE {value:.4g}'
              for name, value in report['heldout']['baselines'].items()]
    verdict = report['verdict']
    lines.append(f'- verdict: {verdict["text"]}')
    if verdict['worse']:  # at the top
        lines[2:2] = [f'**Warning: {verdict["text"]}. The model is written but should not '
                      'be used.**', '']
    online = report['heldout'].get('online_nrmse')
    if online is not None:
        lines.append(f"- the online identifier's model recorded in the bag (last before the "
                     f'held-out part): θ-NRMSE {online:.4g}')
    check = report.get('description_check')
    if check:
        lines += ['', '## The robot description checked against the data', '',
                  f'- {check["text"]}', '', '| joint | description | learned chain | axis (deg) |',
                  '|---|---|---|---|']
        axis = check['axis_deg'] or [math.nan] * len(check['joints'])
        lines += [f'| {name} | {a:.2%} | {b:.2%} | {c:.1f} |' for name, a, b, c in zip(
            check['joints'], check['description_errors'], check['learned_errors'], axis)]
    lines += ['', '## Coverage (training part)', '', '| joint | θ min | θ max | θ std | θ̇ std |',
              '|---|---|---|---|---|']
    cov = data['training']
    for j, name in enumerate(report['joints']):
        lines.append(f'| {name} | {cov["theta_min"][j]:.3f} | {cov["theta_max"][j]:.3f} | '
                     f'{cov["theta_std"][j]:.3f} | {cov["theta_dot_std"][j]:.3f} |')
    lines += ['', '## Log', ''] + [f'- {level}: {text}' for level, text in report['log']]
    if report['figures']:
        lines += ['', '## Figures', ''] + [f'![{name}]({name})' for name in report['figures']]
    elif report['figures_skipped']:
        lines += ['', f'Figures skipped: {report["figures_skipped"]}.']
    return '\n'.join(lines) + '\n'


# -- the run ----------------------------------------------------------------------------------
