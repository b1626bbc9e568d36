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

"""bench/_matlab.py: generated MATLAB model files evaluated vectorised, on small texts."""

import importlib.util
import os

import numpy as np
import pytest
from repo_paths import REPO_ROOT


def _bench_module(name):
    path = os.path.join(REPO_ROOT, 'bench',
                        name + '.py')
    spec = importlib.util.spec_from_file_location('bench_' + name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_matlab = _bench_module('_matlab')
MatlabError, load_function, parse_function = (_matlab.MatlabError, _matlab.load_function,
                                              _matlab.parse_function)

# the shape of Symbolic Math Toolbox output: a header, inputs unpacked, tN temporaries, a
# packed vector read back by index into a matrix literal with continuations
MASS = """\
% generated
function M = get_M(q)
%GET_M
q1 = q(1);
q2 = q(2);
a4 = 0.5;
t2 = cos(q2);
t3 = t2.^2;
Bstack_hat = [t3.*2.0+a4;t2.*(-3.0e-1)+q1.*1.0e-1;1.5];
M = [...
    Bstack_hat(1) , Bstack_hat(2) ;...
    Bstack_hat(2) , Bstack_hat(3) ];
"""

# the shape of a friction file: a constant matrix, its rows, a loop over the joints
FRICTION = """\
function tau_F = get_F(qdot)
    fp = [...
        1.0,2.0;...
        0.5,-0.25];
    A = fp(1,:);
    s = fp(2,:);
    n = length(qdot);
    tau_F = zeros(n,1);
    for i=1:n
        tau_F(i) = -A(i)/(1+exp(-s(i))) + A(i)/(1+exp(-(qdot(i)+s(i))));
    end
"""


def _scalar(text, *values):
    return parse_function(text)(*(np.atleast_1d(np.asarray(v, dtype=float)) for v in values))


def test_mass_matrix_vectorised_equals_each_sample():
    function = parse_function(MASS)
    assert function.inputs == ('q',) and function.output == 'M' and len(function) == 7
    q = np.random.default_rng(1).uniform(-2.0, 2.0, (50, 2))
    m = function(q)
    assert m.shape == (50, 2, 2)
    c = np.cos(q[:, 1])
    expected = np.stack([np.stack([2 * c * c + 0.5, -0.3 * c + 0.1 * q[:, 0]], -1),
                         np.stack([-0.3 * c + 0.1 * q[:, 0], np.full(50, 1.5)], -1)], -2)
    np.testing.assert_allclose(m, expected, rtol=1e-14)
    np.testing.assert_allclose(function(q[7]), expected[7], rtol=1e-14)   # one sample (n,)
    np.testing.assert_array_equal(function(q), m)          # a second call: same result
    np.testing.assert_array_equal(function(q, block=7), m)     # in blocks of 7 samples
    constant = parse_function('function y = f(x)\ny = [1;2];')
    np.testing.assert_array_equal(constant(q, block=7), [1.0, 2.0])


def test_friction_loop_runs_on_whole_vectors():
    qdot = np.array([[0.0, 0.0], [1.0, -2.0], [-0.3, 0.7]])
    out = parse_function(FRICTION)(qdot)
    a, s = np.array([1.0, 2.0]), np.array([0.5, -0.25])
    expected = -a / (1 + np.exp(-s)) + a / (1 + np.exp(-(qdot + s)))
    np.testing.assert_allclose(out, expected, rtol=1e-14)
    np.testing.assert_allclose(out[0], 0.0, atol=1e-15)


@pytest.mark.parametrize('expression, value', [
    ('-2.^2', -4.0),            # power binds tighter than unary minus
    ('2.^-1', 0.5),             # a signed exponent
    ('2^3^2', 64.0),            # powers group from the left
    ('8./2./2', 2.0),
    ('1-2-3', -4.0),
    ('3.*2.^2./4+1', 4.0),
    ('2.*-3', -6.0),
    ('1.5e-1.*2.0', 0.3),
    ('((1+2)).*(-(3))', -9.0),
    ('x.*2.', 6.0),             # "2." then ".*" is not read as "2" ".*"
    ('sqrt(abs(-16)) + pi.*0', 4.0),
])
def test_precedence_as_matlab(expression, value):
    text = f'function y = f(x)\ny = {expression};\n'
    assert _scalar(text, 3.0) == pytest.approx(value, rel=1e-15)


def test_long_sums_and_freed_temporaries():
    count = 3000
    lines = ['function y = f(x)', 't0 = x(1);']
    lines += [f't{k} = t{k - 1}.*1.0+1.0;' for k in range(1, count)]
    lines.append('y = [' + '+'.join(f't{k}' for k in range(count)) + ';t0];')
    function = parse_function('\n'.join(lines))
    x = np.array([[1.0], [2.0]])
    out = function(x)
    expected = sum(x[:, 0] + k for k in range(count))
    np.testing.assert_allclose(out[:, 0], expected)
    np.testing.assert_allclose(out[:, 1], x[:, 0])


@pytest.mark.parametrize('text, says', [
    ('y = 1;', 'function line'),
    ('function y = f(x)\ny = z + 1;', 'z is not defined'),
    ("function y = f(x)\ny = x';", 'transposes'),
    ('function y = f(x)\ny = [x(1) -x(2)];', 'whitespace-separated'),
    ('function y = f(x)\nif x(1)\ny = 1;\nend', "'if' is not supported"),
    ('function y = f(x)\nm = [1,2;3,4];\ny = m(2);', 'matrix'),
    ('function y = f(x)\ny = x(1,2);', 'vector'),
    ('function y = f(x)\ny = x(0);', 'positive integer'),
    ('function y = f(x)\ny = 1;\nend\nz = 2;', 'after the end'),
    ('function y = f(x)\ny = [1;2;\n', 'ends inside'),
    ('function y = f(x)\ny = zeros(2,1);\nfor i=1:2\ny(i) = y(i) + sum(x);\nend',
     'sum is not defined'),
    ('function y = f(x)\ny = zeros(2,1);\nfor i=1:2\ny(i) = x(i) + y;\nend', 'read in the loop'),
    ('function y = f(x)\nfor i=1:2\nz = x(i);\nend\ny = z;', 'in a loop only'),
    ('function y = f(x)\ny = x @ 2;', 'unexpected'),
])
def test_outside_the_subset_is_a_clear_error(text, says):
    with pytest.raises(MatlabError, match=says):
        parse_function(text)


def test_loop_over_part_of_a_vector_is_refused_when_run():
    text = 'function y = f(x)\ny = zeros(3,1);\nfor i=1:2\ny(i) = x(i);\nend'
    function = parse_function(text)
    with pytest.raises(MatlabError, match='passes'):
        function(np.ones((4, 3)))


def test_load_function_names_the_file(tmp_path):
    good = tmp_path / 'get_M.m'
    good.write_text(MASS)
    assert load_function(str(good))(np.zeros(2)).shape == (2, 2)
    bad = tmp_path / 'bad.m'
    bad.write_text('function y = f(x)\ny = w;\n')
    with pytest.raises(MatlabError, match='bad.m: line 2'):
        load_function(str(bad))
