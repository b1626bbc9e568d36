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
The shape of the package, measured: sizes, and where the Gill update and the servo law live.

Run from the package root (any checkout: ``--root`` measures another one)::

    python3 bench/structure.py

Writes ``bench/results/structure.json`` with

- ``max_module_lines``: the longest module under ``rkgnn_ros/`` (lines, as ``wc -l``);
- ``max_class_lines``: the longest class there (from its ``class`` line to its last line,
  docstring included, decorators not);
- ``node_module_lines``: the lines of ``rkgnn_ros/identifier.py``;
- ``rkg_step_definitions``: how many functions define a Runge-Kutta-Gill update, found by
  scanning every function under ``rkgnn_ros/`` for the coefficients that only this method
  uses: Gill's alpha, beta, gamma by name (``ALPHA``, ``rkg.BETA``), any coefficient a
  module imports from ``integration.rkg`` (``D``, ``E``, ``G``, the tableau's ``A``, ``B``)
  by its imported name, and the numeric values of alpha, beta, gamma, d, e, g and of the
  tableau's entries that involve √2; each is listed by file and function. A module-level
  table built from coefficients imported from ``rkg`` (a stepping method as data, such as
  rows of Gill's stages for a generic stage loop) counts too, listed by file and name;
- ``servo_law_definitions``: how many functions write out a servo law, Kp e + Kd ė, listed
  by file and function (``servo_law_definition_sites``). A function counts when one of its
  sums (a chain of ``+``, in any order and nesting) has two product terms (``*`` or ``@``),
  one with a proportional gain among its factors and one with a derivative gain. A factor
  is a proportional gain when its name starts with ``kp`` or ``k_p`` and a derivative gain
  when it starts with ``kd`` or ``k_d`` (case and leading underscores ignored; the name of
  a variable, the attribute of an attribute access, or the array a subscript or ``.T`` is
  taken of: ``kp``, ``self.kp_``, ``c.kp[i]``, ``kp_known[a]``, ``kp.T``); two factors that
  subscript the same array named ``g`` or containing ``gain`` (``gains[0]`` and
  ``gains[1]``, ``g[:, :n]`` and ``g[:, n:]``, ``gains[p, i]`` and ``gains[p, n + i]``)
  count as the two gains. A call of the law's one definition writes nothing out and does
  not count; nor does a sum with a single gain product (``ki * e + Kt (τ - τ_raw)``);
- ``online_policy_constant_modules``: how many modules of the online policy define a
  tunable of it, listed with the names (``online_policy_constants``). The online policy is
  the modules of ``rkgnn_ros/core/fitting/`` that decide what the identification does and
  when (:data:`ONLINE_POLICY`: ``online*.py``, ``policy.py``, the keepers, the rigid
  body's form choice, the change detectors, the search's starts, the excitation memory's
  feed, the validation split); a tunable is a module-level UPPER_CASE name bound to a
  number (a literal, signed, or arithmetic on literals);
- ``max_function_parameters``: the most parameters a function or method under
  ``rkgnn_ros/`` takes (every named one, ``*args`` and ``**kwargs`` one each, a method's
  ``self`` or ``cls`` not), numba kernels (``@njit``, ``@jit`` ...: their arguments are
  arrays by design) left out; the functions over :data:`PARAMETER_LIMIT` are listed
  (``functions_over_parameter_limit``);
- ``top_level_modules``: the Python modules directly in ``rkgnn_ros/`` (``__init__.py``
  not counted);
- ``core_folder_cycles``: how many pairs of folders of ``rkgnn_ros/core/`` import each
  other (listed in ``core_folder_cycle_pairs``);
- ``readme_lines``: the lines of ``README.md``;
- ``duplicate_pairs``: the pairs of places in ``rkgnn_ros/`` that share six or more lines,
  as the ``duplicates`` command counts them (None where it is not installed);
- ``test_suite``: the last recorded run of the whole test suite, ``wall_s`` its wall time
  (``test_suite_wall_s``), read from a pytest log given with ``--suite-log`` (its last
  summary line), else kept from the JSON written before;

and, to say where the limits (600 lines a module, 400 a class) are not met, every module
and class over them. Nothing here imports the package: the files are parsed, not run.
"""

import argparse
import ast
import datetime
import json
import math
import os
import re
import subprocess

HERE = os.path.dirname(os.path.abspath(__file__))
MODULE_LIMIT = 600
CLASS_LIMIT = 400
PARAMETER_LIMIT = 8

#: Decorators of a numba kernel (left out of the parameter count).
KERNEL_DECORATORS = {'njit', 'jit', 'vectorize', 'guvectorize', 'cfunc', 'stencil'}

#: The modules of core/fitting/ that make up the online policy (see the module docstring).
ONLINE_POLICY = ('online.py', 'online_records.py', 'online_rules.py', 'policy.py', 'case_one.py',
                 'case_three.py', 'rigid_online.py', 'rigid_fit.py', 'change.py',
                 'rigid_change.py', 'trig_change.py', 'search_starts.py', 'memory.py',
                 'validation.py')

SQRT2 = math.sqrt(2.0)
#: Gill's alpha, beta, gamma: the coefficients of the accumulator form and nothing else.
GILL_NAMES = {'ALPHA', 'BETA', 'GAMMA'}
#: Names of coefficients that count where a module imports them from ``integration.rkg``.
RKG_COEFFICIENTS = {'ALPHA', 'BETA', 'GAMMA', 'D', 'E', 'G', 'A', 'B'}
#: |value| of alpha, beta, gamma, d, e, g and the tableau's √2 entries (A20, A21, B1, B2).
GILL_VALUES = (abs((SQRT2 - 1.0) / SQRT2), abs(-2.0 + 3.0 / SQRT2), 2.0 + 3.0 / SQRT2,
               (SQRT2 + 1.0) / SQRT2, 2.0 - SQRT2, 2.0 + SQRT2, (SQRT2 - 1.0) / 2.0,
               (2.0 - SQRT2) / 2.0, (2.0 - SQRT2) / 6.0, (2.0 + SQRT2) / 6.0)


def python_files(package):
    """Return every ``.py`` file under ``package``, sorted, as paths."""
    found = []
    for folder, dirs, files in os.walk(package):
        dirs[:] = sorted(d for d in dirs if d != '__pycache__')
        found += [os.path.join(folder, f) for f in sorted(files) if f.endswith('.py')]
    return found


def imported_coefficients(tree):
    """Return the local names a module binds to RKG coefficients imported from ``rkg``."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or '').split('.')[-1] == 'rkg':
            names |= {a.asname or a.name for a in node.names if a.name in RKG_COEFFICIENTS}
    return names


def uses_gill_coefficients(node, imported=frozenset()):
    """
    Return whether a function's body uses a coefficient of the RKG method.

    By name (Gill's alpha, beta, gamma, or a coefficient the module imported from ``rkg``,
    ``imported``) or by value (:data:`GILL_VALUES`).
    """
    for child in ast.walk(node):
        if isinstance(child, ast.Name) and (child.id in GILL_NAMES or child.id in imported):
            return True
        if isinstance(child, ast.Attribute) and child.attr in GILL_NAMES:
            return True
        if isinstance(child, ast.Constant) and isinstance(child.value, float):
            if any(abs(abs(child.value) - v) < 1e-6 for v in GILL_VALUES):
                return True
    return False


def coefficient_tables(tree, imported):
    """Return the names of module-level values built from imported RKG coefficients."""
    found = []
    for stmt in tree.body:
        if isinstance(stmt, ast.Assign):
            targets, value = stmt.targets, stmt.value
        elif isinstance(stmt, ast.AnnAssign) and stmt.value is not None:
            targets, value = [stmt.target], stmt.value
        else:
            continue
        uses = any(isinstance(child, ast.Name) and child.id in imported
                   for child in ast.walk(value))
        if uses:
            found += [t.id for t in targets if isinstance(t, ast.Name)]
    return found


def _gain_name(node):
    """Return the name a factor is known by (see the module docstring), or None."""
    while True:
        if isinstance(node, ast.Subscript):
            node = node.value
        elif isinstance(node, ast.Attribute) and node.attr == 'T':
            node = node.value
        elif isinstance(node, ast.UnaryOp):
            node = node.operand
        else:
            break
    if isinstance(node, ast.Name):
        return node.id.lower().lstrip('_')
    if isinstance(node, ast.Attribute):
        return node.attr.lower().lstrip('_')
    return None


def _gain_array(node):
    """Return the name of the gains array a subscript factor takes, or None."""
    if isinstance(node, ast.Subscript):
        name = _gain_name(node.value)
        if name is not None and (name == 'g' or 'gain' in name):
            return name, ast.dump(node.slice)
    return None


def _sum_terms(node):
    """Return the terms of a chain of additions (flattened), or [node]."""
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
        return _sum_terms(node.left) + _sum_terms(node.right)
    return [node]


def _factors(node):
    """Return the factors of a product term (flattened ``*`` and ``@``), or None."""
    if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Mult, ast.MatMult)):
        return (_factors(node.left) or [node.left]) + (_factors(node.right) or [node.right])
    return None


def _is_servo_law_sum(node):
    """Return whether a chain of additions has a Kp·e term and a Kd·ė term."""
    products = [f for f in (_factors(term) for term in _sum_terms(node)) if f]
    kinds = []
    for factors in products:
        names = {_gain_name(f) or '' for f in factors}
        kinds.append(('p' if any(n.startswith(('kp', 'k_p')) for n in names) else '')
                     + ('d' if any(n.startswith(('kd', 'k_d')) for n in names) else ''))
    if any('p' in a for a in kinds) and any('d' in b for b in kinds) and len(products) > 1:
        p_terms = [i for i, k in enumerate(kinds) if 'p' in k]
        d_terms = [i for i, k in enumerate(kinds) if 'd' in k]
        if any(i != j for i in p_terms for j in d_terms):
            return True
    arrays = [{_gain_array(f) for f in factors} - {None} for factors in products]
    for i, a in enumerate(arrays):
        for b in arrays[i + 1:]:
            if any(x[0] == y[0] and x[1] != y[1] for x in a for y in b):
                return True
    return False


def writes_servo_law(function):
    """Return whether a function's own body (not a nested one's) writes out a servo law."""
    todo = list(ast.iter_child_nodes(function))
    while todo:
        child = todo.pop()
        if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda,
                              ast.ClassDef)):
            continue
        if isinstance(child, ast.BinOp) and isinstance(child.op, ast.Add) \
                and _is_servo_law_sum(child):
            return True
        todo.extend(ast.iter_child_nodes(child))
    return False


def qualified_functions(tree):
    """Yield ``(qualified name, function node)`` for every function of a module."""
    todo = [('', node) for node in tree.body]
    while todo:
        prefix, node = todo.pop(0)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            name = prefix + node.name
            if not isinstance(node, ast.ClassDef):
                yield name, node
            todo.extend((name + '.', child) for child in node.body)
        else:
            todo.extend((prefix, child) for child in ast.iter_child_nodes(node)
                        if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef,
                                              ast.ClassDef, ast.If, ast.Try, ast.With)))


def _is_number(node):
    """Return whether an expression is a number: a literal, signed, or arithmetic on them."""
    if isinstance(node, ast.Constant):
        return isinstance(node.value, (int, float)) and not isinstance(node.value, bool)
    if isinstance(node, ast.UnaryOp):
        return _is_number(node.operand)
    if isinstance(node, ast.BinOp):
        return _is_number(node.left) and _is_number(node.right)
    return False


def numeric_constants(tree):
    """Return the UPPER_CASE names a module binds at module level to a number."""
    found = []
    for stmt in tree.body:
        if isinstance(stmt, ast.Assign):
            targets, value = stmt.targets, stmt.value
        elif isinstance(stmt, ast.AnnAssign) and stmt.value is not None:
            targets, value = [stmt.target], stmt.value
        else:
            continue
        if _is_number(value):
            found += [t.id for t in targets if isinstance(t, ast.Name) and t.id.isupper()]
    return found


def _decorator_name(node):
    """Return the last name of a decorator (``numba.njit(cache=True)`` -> ``njit``)."""
    node = node.func if isinstance(node, ast.Call) else node
    return node.attr if isinstance(node, ast.Attribute) else getattr(node, 'id', '')


def parameter_counts(tree, rel):
    """Yield (parameters, 'file:qualified name') of every function but numba kernels."""
    def walk(node, in_class, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if not any(_decorator_name(d) in KERNEL_DECORATORS
                           for d in child.decorator_list):
                    a = child.args
                    names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs]
                    if in_class and names and names[0] in ('self', 'cls'):
                        names = names[1:]
                    count = len(names) + (a.vararg is not None) + (a.kwarg is not None)
                    yield count, f'{rel}:{prefix}{child.name}'
                yield from walk(child, False, f'{prefix}{child.name}.')
            elif isinstance(child, ast.ClassDef):
                yield from walk(child, True, f'{prefix}{child.name}.')
            else:
                yield from walk(child, in_class, prefix)
    yield from walk(tree, False, '')


def core_cycles(package):
    """Return the pairs of folders of ``core/`` that import each other."""
    core = os.path.join(package, 'core')
    folders = {name for name in os.listdir(core)
               if os.path.isdir(os.path.join(core, name)) and not name.startswith('_')}
    edges = set()
    for path in python_files(core):
        parts = os.path.relpath(path, core).split(os.sep)
        if len(parts) < 2:
            continue
        with open(path, encoding='utf-8') as f:
            tree = ast.parse(f.read())
        for node in ast.walk(tree):
            if not isinstance(node, ast.ImportFrom) or node.module is None:
                continue
            names = node.module.split('.')
            if node.level == 2 and names[0] in folders:
                target = names[0]
            elif 'core' in names and names.index('core') + 1 < len(names):
                target = names[names.index('core') + 1]
            else:
                continue
            if target in folders and target != parts[0]:
                edges.add((parts[0], target))
    return sorted({tuple(sorted(e)) for e in edges if (e[1], e[0]) in edges})


def duplicate_pairs(package):
    """Return the pairs the ``duplicates`` command counts in ``package`` (None: no command)."""
    try:
        out = subprocess.run(['duplicates', '--repo', package, '--most', '200',
                              '--seconds', '120'], capture_output=True, text=True,
                             check=False).stdout
    except OSError:
        return None
    first = out.strip().splitlines()[0] if out.strip() else ''
    if first.startswith('no duplicates'):
        return 0
    match = re.match(r'(\d+) pairs? of places', first)
    return int(match.group(1)) if match else None


def suite_run(log):
    """Return the summary of a pytest log: passed, failed, skipped and wall_s."""
    with open(log, encoding='utf-8', errors='replace') as f:
        lines = [line for line in f if re.search(r' in [\d.]+s', line)]
    if not lines:
        raise ValueError(f'{log}: no pytest summary line')
    summary = lines[-1]
    counts = re.findall(r'(\d+) (passed|failed|skipped|errors?)', summary)
    run = {key: int(n) for n, key in counts}
    run['wall_s'] = float(re.search(r' in ([\d.]+)s', summary).group(1))
    return run


def measure(root):
    """Return the measurements of the checkout at ``root`` as a dict."""
    package = os.path.join(root, 'rkgnn_ros')
    modules, classes, gill, laws, policy, parameters = [], [], [], [], {}, []
    for path in python_files(package):
        rel = os.path.relpath(path, root)
        with open(path, encoding='utf-8') as f:
            text = f.read()
        modules.append((text.count('\n'), rel))
        tree = ast.parse(text, filename=rel)
        imported = imported_coefficients(tree)
        gill += [f'{rel}:{name}' for name in coefficient_tables(tree, imported)]
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                classes.append((node.end_lineno - node.lineno + 1, f'{rel}:{node.name}'))
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if uses_gill_coefficients(node, imported):
                    gill.append(f'{rel}:{node.name}')
        laws += [f'{rel}:{name}' for name, node in qualified_functions(tree)
                 if writes_servo_law(node)]
        parameters += parameter_counts(tree, rel)
        folder, name = os.path.split(rel)
        if folder == os.path.join('rkgnn_ros', 'core', 'fitting') and name in ONLINE_POLICY:
            constants = numeric_constants(tree)
            if constants:
                policy[rel] = constants
    modules.sort(reverse=True)
    classes.sort(reverse=True)
    node = os.path.join(package, 'identifier.py')
    node_lines = None
    if os.path.exists(node):
        with open(node, encoding='utf-8') as f:
            node_lines = f.read().count('\n')
    parameters.sort(key=lambda item: (-item[0], item[1]))
    cycles = core_cycles(package)
    top = [name for name in os.listdir(package)
           if name.endswith('.py') and name != '__init__.py']
    readme = os.path.join(root, 'README.md')
    readme_lines = None
    if os.path.exists(readme):
        with open(readme, encoding='utf-8') as f:
            readme_lines = len(f.read().splitlines())
    return {
        'max_module_lines': modules[0][0],
        'max_module': modules[0][1],
        'max_class_lines': classes[0][0],
        'max_class': classes[0][1],
        'node_module_lines': node_lines,
        'rkg_step_definitions': len(gill),
        'rkg_step_definition_sites': gill,
        'servo_law_definitions': len(laws),
        'servo_law_definition_sites': laws,
        'online_policy_constant_modules': len(policy),
        'online_policy_constants': policy,
        'max_function_parameters': parameters[0][0],
        'functions_over_parameter_limit': {name: count for count, name in parameters
                                           if count > PARAMETER_LIMIT},
        'top_level_modules': len(top),
        'core_folder_cycles': len(cycles),
        'core_folder_cycle_pairs': [list(pair) for pair in cycles],
        'readme_lines': readme_lines,
        'duplicate_pairs': duplicate_pairs(package),
        'modules_over_limit': {name: lines for lines, name in modules if lines > MODULE_LIMIT},
        'classes_over_limit': {name: lines for lines, name in classes if lines > CLASS_LIMIT},
        'limits': {'module_lines': MODULE_LIMIT, 'class_lines': CLASS_LIMIT},
        'modules': len(modules),
    }


def commit(root):
    """Return the checkout's commit, or None outside git."""
    try:
        return subprocess.run(['git', 'rev-parse', 'HEAD'], cwd=root, check=True,
                              capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--root', default=os.path.dirname(HERE),
                        help='checkout to measure (default: this one)')
    parser.add_argument('--out', default=os.path.join(HERE, 'results', 'structure.json'),
                        help="where to write the JSON ('-': print only)")
    parser.add_argument('--suite-log', default=None,
                        help='pytest log of a run of the whole suite (default: the run '
                             'recorded in --out before)')
    args = parser.parse_args(argv)
    result = measure(os.path.abspath(args.root))
    if args.suite_log is not None:
        result['test_suite'] = dict(suite_run(args.suite_log),
                                    log=os.path.basename(args.suite_log))
    elif args.out != '-' and os.path.exists(args.out):
        with open(args.out, encoding='utf-8') as f:
            result['test_suite'] = json.load(f).get('test_suite')
    suite = result.get('test_suite') or {}
    result['test_suite_wall_s'] = suite.get('wall_s')
    result['commit'] = commit(args.root)
    result['date'] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')
    text = json.dumps(result, indent=2)
    print(text)
    if args.out != '-':
        with open(args.out, 'w', encoding='utf-8') as f:
            f.write(text + '\n')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
