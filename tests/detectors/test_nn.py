"""numpy layers: forward against direct sums, backward against central finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.detectors.nn import (
    Adam,
    Conv1d,
    Dense,
    Relu,
    Sequential,
    Tanh,
    mse_loss,
)


def numeric_gradient(function, array: np.ndarray, step: float = 1e-6) -> np.ndarray:
    """Central differences of a function with respect to every element of ``array``.

    ``function()`` returns a scalar or an array of shape S (several functions of the same
    perturbed inputs at once); the result has shape ``(*array.shape, *S)``.
    """
    flat = array.reshape(-1)
    differences = []
    for i in range(flat.size):
        saved = flat[i]
        flat[i] = saved + step
        plus = np.asarray(function(), dtype=np.float64)
        flat[i] = saved - step
        minus = np.asarray(function(), dtype=np.float64)
        flat[i] = saved
        differences.append((plus - minus) / (2.0 * step))
    return np.stack(differences).reshape(*array.shape, *differences[0].shape)


def check_layer(layer, x: np.ndarray, rng: np.random.Generator) -> None:
    """Loss = sum(y * c) for a fixed random c: analytic vs numeric gradients of x and params."""
    y = layer.forward(x)
    weights = rng.standard_normal(y.shape)

    def loss() -> float:
        return float(np.sum(layer.forward(x) * weights))

    layer.forward(x)
    grad_x = layer.backward(weights)
    analytic_params = [g.copy() for g in layer.grads]
    assert_allclose(grad_x, numeric_gradient(loss, x), rtol=1e-6, atol=1e-8)
    for param, analytic in zip(layer.params, analytic_params):
        assert_allclose(analytic, numeric_gradient(loss, param), rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize(("kernel", "stride", "length"), [(3, 1, 9), (4, 2, 11), (5, 3, 5)])
def test_conv1d_gradients(kernel, stride, length):
    rng = np.random.default_rng(1)
    layer = Conv1d(2, 3, kernel, stride, rng)
    layer.params[1][:] = rng.standard_normal(3)
    check_layer(layer, rng.standard_normal((4, length, 2)), rng)


def test_conv1d_forward_is_the_direct_sum():
    rng = np.random.default_rng(2)
    layer = Conv1d(3, 2, 4, 2, rng)
    layer.params[1][:] = [0.5, -1.0]
    x = rng.standard_normal((2, 10, 3))
    y = layer.forward(x)
    weight, bias = layer.params
    assert y.shape == (2, 4, 2) == (2, *layer.output_shape((10, 3)))
    expected = np.zeros((2, 4, 2))
    for b in range(2):
        for t in range(4):
            for o in range(2):
                expected[b, t, o] = bias[o] + sum(
                    x[b, 2 * t + k, c] * weight[c, k, o] for k in range(4) for c in range(3)
                )
    assert_allclose(y, expected, rtol=1e-12)


def test_conv1d_rejects_short_input():
    layer = Conv1d(1, 1, 5, 1, np.random.default_rng(0))
    with pytest.raises(ValueError, match="shorter than kernel"):
        layer.forward(np.zeros((1, 4, 1)))


def test_dense_gradients():
    rng = np.random.default_rng(3)
    layer = Dense(12, 3, rng)
    layer.params[1][:] = rng.standard_normal(3)
    check_layer(layer, rng.standard_normal((5, 4, 3)), rng)


@pytest.mark.parametrize("activation", [Relu, Tanh])
def test_activation_gradients(activation):
    rng = np.random.default_rng(4)
    x = rng.standard_normal((3, 7, 2))
    x[np.abs(x) < 1e-3] = 0.1  # keep away from the ReLU kink
    check_layer(activation(), x, rng)


def test_activation_values():
    x = np.array([[-2.0, 0.0, 3.0]])
    assert_allclose(Relu().forward(x), [[0.0, 0.0, 3.0]])
    assert_allclose(Tanh().forward(x), np.tanh(x))


def test_mse_loss_value_and_gradient():
    rng = np.random.default_rng(5)
    prediction = rng.standard_normal((6, 3))
    target = rng.standard_normal((6, 3))
    loss, grad = mse_loss(prediction, target)
    assert_allclose(loss, np.mean((prediction - target) ** 2))
    numeric = numeric_gradient(lambda: mse_loss(prediction, target)[0], prediction)
    assert_allclose(grad, numeric, rtol=1e-6, atol=1e-10)


def test_whole_network_gradient_and_input_jacobian():
    rng = np.random.default_rng(6)
    net = Sequential(
        [Conv1d(3, 4, 5, 1, rng), Tanh(), Conv1d(4, 4, 3, 2, rng), Tanh(), Dense(4 * 5, 2, rng)]
    )
    x = rng.standard_normal((3, 16, 3))
    target = rng.standard_normal((3, 2))

    def loss() -> float:
        return mse_loss(net.forward(x), target)[0]

    _, grad = mse_loss(net.forward(x), target)
    grad_x = net.backward(grad)
    analytic = [g.copy() for g in net.grads]
    for param, g in zip(net.params, analytic):
        assert_allclose(g, numeric_gradient(loss, param), rtol=1e-5, atol=1e-9)
    assert_allclose(grad_x, numeric_gradient(loss, x), rtol=1e-5, atol=1e-9)
    jacobian = net.input_gradients(x)
    assert jacobian.shape == (3, 2, 16, 3)
    # d sum_b y[b, o] / dx of both outputs from one set of 288 perturbed forward passes
    numeric = numeric_gradient(lambda: net.forward(x).sum(axis=0), x)  # (3, 16, 3, 2)
    for o in range(2):
        assert_allclose(jacobian[:, o], numeric[..., o], rtol=1e-5, atol=1e-9)


def test_adam_first_step_and_convergence():
    param = np.array([1.0, -2.0])
    optimiser = Adam([param], learning_rate=0.1)
    optimiser.step([np.array([0.5, -3.0])])
    # bias-corrected first step moves every coordinate by lr * sign(grad)
    assert_allclose(param, [0.9, -1.9], rtol=1e-6)
    for _ in range(500):
        optimiser.step([2.0 * param])  # minimise |param|^2
    assert_allclose(param, [0.0, 0.0], atol=1e-2)


def test_training_fits_a_linear_filter():
    """A conv+dense network trained with Adam learns y = x[-1] - x[-2] (a differencer).
    128 examples for its 41 parameters (512 take twice the CPU: 0.22 against 0.11 s); the
    final loss was under 1e-15 on each of seeds 0-19 (512 examples: under 1e-6)."""
    rng = np.random.default_rng(7)
    x = rng.standard_normal((128, 8, 1))
    y = x[:, -1, :] - x[:, -2, :]
    net = Sequential([Conv1d(1, 4, 3, 1, rng), Dense(4 * 6, 1, rng)])
    optimiser = Adam(net.params, learning_rate=0.01)
    for _ in range(400):
        _, grad = mse_loss(net.forward(x), y)
        net.backward(grad)
        optimiser.step(net.grads)
    assert mse_loss(net.forward(x), y)[0] < 1e-4


def test_skipped_gradients_change_nothing_that_is_computed():
    """``input_grad=False`` gives the same parameter gradients, ``param_grads=False`` the same
    input gradient and leaves ``grads`` as they were, and ``input_gradients`` (one forward
    pass, no parameter gradients) is exactly a forward and a full backward pass per output."""
    rng = np.random.default_rng(8)
    net = Sequential(
        [Conv1d(3, 4, 5, 1, rng), Relu(), Conv1d(4, 4, 3, 2, rng), Tanh(), Dense(4 * 5, 2, rng)]
    )
    x = rng.standard_normal((6, 16, 3))
    _, grad = mse_loss(net.forward(x), rng.standard_normal((6, 2)))
    full_input = net.backward(grad)
    full_params = [g.copy() for g in net.grads]
    assert net.backward(grad, input_grad=False).size == 0
    for g, expected in zip(net.grads, full_params):
        np.testing.assert_array_equal(g, expected)
    stale = [np.full_like(g, 7.0) for g in net.grads]
    for layer in net.layers:
        layer.grads = [s.copy() for s in stale[: len(layer.grads)]]
        stale = stale[len(layer.grads) :]
    np.testing.assert_array_equal(net.backward(grad, param_grads=False), full_input)
    assert all(np.all(g == 7.0) for g in net.grads)
    jacobian = net.input_gradients(x)
    assert all(np.all(g == 7.0) for g in net.grads)
    for o in range(2):
        outputs = net.forward(x)
        seed = np.zeros_like(outputs)
        seed[:, o] = 1.0
        np.testing.assert_array_equal(jacobian[:, o], net.backward(seed))
