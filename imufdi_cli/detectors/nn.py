"""A minimal numpy neural-network toolkit: 1-D convolution, dense layer, activations, MSE loss,
Adam, and a sequential network with vectorised forward and backward passes.

Used by the cnn-map detector (:mod:`imufdi_cli.detectors.cnn_map`). Tensors are channels-last:
a batch of sequences has shape (B, L, C) (batch, time, channel). Convolutions use im2col via
``numpy.lib.stride_tricks.sliding_window_view`` so that a whole batch is one matrix product;
the backward pass scatters the column gradients back with one strided add per kernel tap.

Every layer keeps what its backward pass needs from the last ``forward`` call (``backward``
only reads it, so one forward pass serves several backward passes); ``backward`` takes
dLoss/dOutput, stores the parameter gradients in ``grads`` (same order as ``params``) and
returns dLoss/dInput. Either can be skipped (``param_grads=False``: ``grads`` keep their
last values; ``input_grad=False``: an empty array is returned), e.g. the parameter gradients
when only the input gradient is wanted, or the first layer's input gradient in training.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view


class Layer:
    """Base class: no parameters, identity."""

    params: list[np.ndarray]
    grads: list[np.ndarray]

    def __init__(self) -> None:
        self.params = []
        self.grads = []

    def forward(self, x: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def backward(
        self, grad_out: np.ndarray, param_grads: bool = True, input_grad: bool = True
    ) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def output_shape(self, input_shape: tuple[int, ...]) -> tuple[int, ...]:
        """Shape of one sample's output for one sample's input shape (no batch axis)."""
        return input_shape


class Conv1d(Layer):
    """Valid 1-D convolution (cross-correlation), channels-last.

    ``y[b, t, o] = bias[o] + sum_{k, c} x[b, stride t + k, c] W[c, k, o]``

    Parameters
    ----------
    in_channels, out_channels, kernel : int
    stride : int
    rng : numpy.random.Generator
        He-uniform initialisation of W, zero bias.

    Shapes: input (B, L, in_channels) -> output (B, (L - kernel) // stride + 1, out_channels).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel: int,
        stride: int,
        rng: np.random.Generator,
    ) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel = kernel
        self.stride = stride
        fan_in = in_channels * kernel
        limit = np.sqrt(6.0 / fan_in)
        weight = rng.uniform(-limit, limit, size=(in_channels, kernel, out_channels))
        self.params = [weight, np.zeros(out_channels)]
        self.grads = [np.zeros_like(p) for p in self.params]
        self._columns: np.ndarray | None = None
        self._input_shape: tuple[int, ...] = ()

    def output_shape(self, input_shape: tuple[int, ...]) -> tuple[int, ...]:
        length = (input_shape[0] - self.kernel) // self.stride + 1
        return (length, self.out_channels)

    def forward(self, x: np.ndarray) -> np.ndarray:
        batch, length, channels = x.shape
        out_length = (length - self.kernel) // self.stride + 1
        if out_length < 1:
            raise ValueError(f"sequence of {length} samples is shorter than kernel {self.kernel}")
        # (B, L - K + 1, C, K) -> every stride-th window -> (B, L_out, C * K)
        windows = sliding_window_view(x, self.kernel, axis=1)[:, :: self.stride][:, :out_length]
        columns = windows.reshape(batch, out_length, channels * self.kernel)
        self._columns = columns
        self._input_shape = x.shape
        weight, bias = self.params
        return columns @ weight.reshape(channels * self.kernel, self.out_channels) + bias  # type: ignore[no-any-return]

    def backward(
        self, grad_out: np.ndarray, param_grads: bool = True, input_grad: bool = True
    ) -> np.ndarray:
        assert self._columns is not None
        columns = self._columns
        batch, out_length, width = columns.shape
        weight = self.params[0]
        flat_weight = weight.reshape(width, self.out_channels)
        if param_grads:
            self.grads[0] = (
                columns.reshape(-1, width).T @ grad_out.reshape(-1, self.out_channels)
            ).reshape(weight.shape)
            self.grads[1] = grad_out.sum(axis=(0, 1))
        if not input_grad:
            return np.empty(0)
        grad_columns = (grad_out @ flat_weight.T).reshape(
            batch, out_length, self.in_channels, self.kernel
        )
        grad_input = np.zeros(self._input_shape)
        span = self.stride * (out_length - 1) + 1
        for tap in range(self.kernel):  # K strided adds, not a per-sample loop
            grad_input[:, tap : tap + span : self.stride, :] += grad_columns[:, :, :, tap]
        return grad_input


class Dense(Layer):
    """Fully connected layer on flattened samples: (B, ...) -> (B, out_features).

    ``y = x_flat W + bias``, W (in_features, out_features), Glorot-uniform initialisation.
    """

    def __init__(self, in_features: int, out_features: int, rng: np.random.Generator) -> None:
        super().__init__()
        limit = np.sqrt(6.0 / (in_features + out_features))
        self.params = [
            rng.uniform(-limit, limit, size=(in_features, out_features)),
            np.zeros(out_features),
        ]
        self.grads = [np.zeros_like(p) for p in self.params]
        self._input: np.ndarray | None = None
        self._input_shape: tuple[int, ...] = ()

    def output_shape(self, input_shape: tuple[int, ...]) -> tuple[int, ...]:
        return (self.params[0].shape[1],)

    def forward(self, x: np.ndarray) -> np.ndarray:
        self._input_shape = x.shape
        flat = x.reshape(x.shape[0], -1)
        self._input = flat
        return flat @ self.params[0] + self.params[1]  # type: ignore[no-any-return]

    def backward(
        self, grad_out: np.ndarray, param_grads: bool = True, input_grad: bool = True
    ) -> np.ndarray:
        assert self._input is not None
        if param_grads:
            self.grads[0] = self._input.T @ grad_out
            self.grads[1] = grad_out.sum(axis=0)
        if not input_grad:
            return np.empty(0)
        return (grad_out @ self.params[0].T).reshape(self._input_shape)  # type: ignore[no-any-return]


class Relu(Layer):
    """``max(x, 0)`` elementwise."""

    def __init__(self) -> None:
        super().__init__()
        self._positive: np.ndarray | None = None

    def forward(self, x: np.ndarray) -> np.ndarray:
        self._positive = x > 0.0
        return np.where(self._positive, x, 0.0)

    def backward(
        self, grad_out: np.ndarray, param_grads: bool = True, input_grad: bool = True
    ) -> np.ndarray:
        assert self._positive is not None
        if not input_grad:
            return np.empty(0)
        return np.where(self._positive, grad_out, 0.0)


class Tanh(Layer):
    """``tanh(x)`` elementwise."""

    def __init__(self) -> None:
        super().__init__()
        self._output: np.ndarray | None = None

    def forward(self, x: np.ndarray) -> np.ndarray:
        self._output = np.tanh(x)
        return self._output

    def backward(
        self, grad_out: np.ndarray, param_grads: bool = True, input_grad: bool = True
    ) -> np.ndarray:
        assert self._output is not None
        if not input_grad:
            return np.empty(0)
        return grad_out * (1.0 - self._output**2)  # type: ignore[no-any-return]


ACTIVATIONS: dict[str, type[Layer]] = {"relu": Relu, "tanh": Tanh}


def mse_loss(prediction: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray]:
    """Mean squared error over every element and its gradient.

    Returns
    -------
    loss : float
        ``mean((prediction - target)^2)``
    grad : ndarray, same shape as ``prediction``
        ``2 (prediction - target) / prediction.size``
    """
    error = prediction - target
    return float(np.mean(error**2)), 2.0 * error / error.size


class Sequential:
    """Layers applied in order; ``forward``, ``backward`` and flat parameter access."""

    def __init__(self, layers: list[Layer]) -> None:
        self.layers = layers

    @property
    def params(self) -> list[np.ndarray]:
        return [p for layer in self.layers for p in layer.params]

    @property
    def grads(self) -> list[np.ndarray]:
        return [g for layer in self.layers for g in layer.grads]

    def forward(self, x: np.ndarray) -> np.ndarray:
        for layer in self.layers:
            x = layer.forward(x)
        return x

    def backward(
        self, grad_out: np.ndarray, param_grads: bool = True, input_grad: bool = True
    ) -> np.ndarray:
        """Back-propagate dLoss/dOutput through the layers of the last ``forward``.

        ``param_grads=False`` leaves every layer's ``grads`` as they were (input gradients
        only); ``input_grad=False`` skips dLoss/dInput of the first layer, which training
        does not use (an empty array is returned). Neither changes what is computed.
        """
        last = len(self.layers) - 1
        for index, layer in enumerate(reversed(self.layers)):
            grad_out = layer.backward(grad_out, param_grads, input_grad or index < last)
        return grad_out

    def predict(self, x: np.ndarray, batch_size: int = 4096) -> np.ndarray:
        """Forward pass in batches (bounded memory)."""
        if x.shape[0] <= batch_size:
            return self.forward(x)
        return np.concatenate(
            [self.forward(x[i : i + batch_size]) for i in range(0, x.shape[0], batch_size)]
        )

    def input_gradients(self, x: np.ndarray) -> np.ndarray:
        """Jacobian of every output with respect to the input, per sample.

        Parameters
        ----------
        x : ndarray, shape (B, ...)

        Returns
        -------
        ndarray, shape (B, n_outputs, ...)
            ``[b, o, ...] = d y[b, o] / d x[b, ...]`` (one forward pass, one backward pass
            per output without the parameter gradients: ``grads`` are left as they were).
        """
        outputs = self.forward(x)
        n_outputs = outputs.shape[1]
        jacobian = np.empty((x.shape[0], n_outputs, *x.shape[1:]))
        seed = np.zeros_like(outputs)
        for o in range(n_outputs):
            seed[:, o] = 1.0
            jacobian[:, o] = self.backward(seed, param_grads=False)
            seed[:, o] = 0.0
        return jacobian


class Adam:
    """Adam optimiser (Kingma & Ba, ICLR 2015, Algorithm 1) on a list of arrays, in place."""

    def __init__(
        self,
        params: list[np.ndarray],
        learning_rate: float = 1e-3,
        beta1: float = 0.9,
        beta2: float = 0.999,
        epsilon: float = 1e-8,
    ) -> None:
        self.params = params
        self.learning_rate = learning_rate
        self.beta1 = beta1
        self.beta2 = beta2
        self.epsilon = epsilon
        self.first = [np.zeros_like(p) for p in params]
        self.second = [np.zeros_like(p) for p in params]
        self.steps = 0

    def step(self, grads: list[np.ndarray]) -> None:
        self.steps += 1
        correction1 = 1.0 - self.beta1**self.steps
        correction2 = 1.0 - self.beta2**self.steps
        for param, grad, first, second in zip(self.params, grads, self.first, self.second):
            first *= self.beta1
            first += (1.0 - self.beta1) * grad
            second *= self.beta2
            second += (1.0 - self.beta2) * grad**2
            param -= (
                self.learning_rate
                * (first / correction1)
                / (np.sqrt(second / correction2) + self.epsilon)
            )
