"""cnn-map's mapping test (paper §2-3): network training or loading, residual calibration
(prewhitening, axis gains, energy ratio to the other IMUs), the per-block test and
episode isolation, model files.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from imufdi_cli.detectors.base import (
    NO_ISOLATION,
    DetectionBlock,
)
from imufdi_cli.detectors.cnn_map.input_test import _InputTest
from imufdi_cli.detectors.cnn_map.network import MappingNetwork
from imufdi_cli.detectors.cnn_map.signals import (
    fit_autoregression,
    gamma_shape,
    input_windows,
    whiten,
)
from imufdi_cli.detectors.moving import MovingWindow
from imufdi_cli.detectors.nn import Adam, mse_loss
from imufdi_cli.errors import (
    CalibrationError,
    DetectorConfigError,
)
from imufdi_cli.log import ImuBlock
from imufdi_cli.maths.quantiles import gamma as gamma_distribution


class _MappingTest(_InputTest):
    """Training, calibration and the online mapping test of :class:`CnnMapDetector`."""

    def _load(self, path: str) -> MappingNetwork:
        try:
            data = Path(path).read_bytes()
        except OSError as err:
            raise DetectorConfigError(f"cnn-map.model: cannot read {path!r} ({err})") from err
        mapping = MappingNetwork.from_npz_bytes(data, f"cnn-map.model {path!r}")
        assert self.array is not None
        if not math.isclose(mapping.rate_hz, self.array.rate_hz, rel_tol=1e-6):
            raise DetectorConfigError(
                f"cnn-map.model: trained at {mapping.rate_hz:g} Hz but the array runs at"
                f" {self.array.rate_hz:g} Hz; retrain without model="
            )
        return mapping

    def _train(
        self,
        body: np.ndarray,
        reference: np.ndarray,
        length: int,
        n_train: int,
        holdout_start: int,
        rate_hz: float,
    ) -> None:
        """Adam on shuffled mini-batches, early stopping on the held-out windows (paper §2)."""
        rng = np.random.default_rng(self.seed)
        windows = input_windows(body, length)  # (W, m, L, 3)
        targets = reference[length - 1 :]  # (W, 3)
        m = windows.shape[1]
        train_x = windows[:n_train].reshape(-1, length, 3)
        train_y = np.repeat(targets[:n_train], m, axis=0)
        hold_x = windows[holdout_start:].reshape(-1, length, 3)
        hold_y = np.repeat(targets[holdout_start:], m, axis=0)
        flat = body[: n_train + length - 1].reshape(-1, 3)
        input_mean, input_std = flat.mean(axis=0), flat.std(axis=0)
        output_mean, output_std = targets[:n_train].mean(axis=0), targets[:n_train].std(axis=0)
        if np.any(input_std <= 0) or np.any(output_std <= 0):
            raise CalibrationError(
                "cnn-map: no motion in the calibration window (constant specific force or rate);"
                " the mapping needs a window with motion"
            )
        mapping = MappingNetwork(
            input_length=length,
            filters=self.filters,
            kernel=self.kernel,
            activation=self.activation,
            rate_hz=float(rate_hz),
            input_mean=input_mean,
            input_std=input_std,
            output_mean=output_mean,
            output_std=output_std,
        )
        network = mapping.build(rng)
        train_in = (train_x - input_mean) / input_std
        train_out = (train_y - output_mean) / output_std
        hold_in = (hold_x - input_mean) / input_std
        hold_out = (hold_y - output_mean) / output_std
        optimiser = Adam(network.params, learning_rate=self.learning_rate)
        train_curve: list[float] = []
        hold_curve: list[float] = []
        best_loss, best_epoch = math.inf, -1
        best = [p.copy() for p in network.params]
        n = train_in.shape[0]
        for epoch in range(self.epochs):
            order = rng.permutation(n)
            total = 0.0
            for start in range(0, n, self.batch):
                pick = order[start : start + self.batch]
                loss, grad = mse_loss(network.forward(train_in[pick]), train_out[pick])
                network.backward(grad, input_grad=False)
                optimiser.step(network.grads)
                total += loss * pick.size
            train_curve.append(total / n)
            hold_loss = mse_loss(network.predict(hold_in), hold_out)[0]
            hold_curve.append(hold_loss)
            if hold_loss < best_loss:
                best_loss, best_epoch = hold_loss, epoch
                best = [p.copy() for p in network.params]
            elif epoch - best_epoch >= self.patience:
                break
        for param, value in zip(network.params, best):
            param[...] = value
        train_mae = np.abs(network.predict(train_in) * output_std + output_mean - train_y)
        hold_mae = np.abs(network.predict(hold_in) * output_std + output_mean - hold_y)
        mapping.weights = [p.copy() for p in network.params]
        mapping.training = {
            "train_windows": int(n),
            "holdout_windows": int(hold_in.shape[0]),
            "epochs_run": len(train_curve),
            "best_epoch": int(best_epoch),
            "train_loss": [float(v) for v in train_curve],
            "holdout_loss": [float(v) for v in hold_curve],
            "mae_rad_s": float(hold_mae.mean()),
            "mae_rad_s_per_axis": hold_mae.mean(axis=0).tolist(),
            "train_mae_rad_s": float(train_mae.mean()),
            "reference_rms_rad_s": float(np.sqrt(np.mean(targets**2))),
        }
        self.mapping = mapping
        self.network = network

    def _predict(self, windows: np.ndarray) -> np.ndarray:
        """Mapped rate (..., 3) rad/s of windows (..., L, 3) of body specific force."""
        assert self.mapping is not None and self.network is not None
        mp = self.mapping
        lead = windows.shape[:-2]
        flat = windows.reshape(-1, mp.input_length, 3)
        out = self.network.predict((flat - mp.input_mean) / mp.input_std)
        return (out * mp.output_std + mp.output_mean).reshape(*lead, 3)  # type: ignore[no-any-return]

    def _residuals(self, predicted: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """Mapping residuals (N, m, 3) rad/s of predictions (N, m, 3) against the reference
        (N, 3) (step 3)."""
        return predicted - reference[:, None, :]  # type: ignore[no-any-return]

    def _axis_gains(self, windows: np.ndarray) -> np.ndarray:
        """Linearised noise gains of the whitened mapping residual, per IMU axis (step 6).

        ``G[n, k, a, c] = sum_lags ((K_c * J_c) . R_k[:, a])^2``, J = d CNN_c / d input
        (rad/s per m/s^2, body frame) of window n of IMU k, K_c the whitening kernel
        ``[1, -phi_c1, .., -phi_cp]`` convolved along the lags: white noise of variance
        delta on IMU axis a adds ``delta G[.., a, c]`` to the variance of whitened
        component c.

        Parameters
        ----------
        windows : ndarray, shape (n, m, L, 3)

        Returns
        -------
        ndarray, shape (n, m, 3, 3), (rad/s)^2 per (m/s^2)^2
        """
        assert self.mapping is not None and self.network is not None
        mp = self.mapping
        n, m = windows.shape[:2]
        flat = ((windows - mp.input_mean) / mp.input_std).reshape(-1, mp.input_length, 3)
        gains = np.empty((flat.shape[0], 3, 3))
        rotations = np.broadcast_to(self.rotations, (n, m, 3, 3)).reshape(-1, 3, 3)
        scale = mp.output_std[None, :, None, None] / mp.input_std[None, None, None, :]
        kernel = np.concatenate([np.ones((3, 1)), -self.ar_coefficients], axis=1)  # (c, p+1)
        p = kernel.shape[1] - 1
        length = mp.input_length
        for lo in range(0, flat.shape[0], 2048):  # bounded memory
            jac = self.network.input_gradients(flat[lo : lo + 2048]) * scale  # (b, c, L, 3)
            rotation = rotations[lo : lo + 2048]
            # directed[b, a, c, l] = sum_j jac[b, c, l, j] R[b, j, a], the terms added in
            # the order einsum("bclj,bja->bacl") adds them (the same floats; 2.7x quicker),
            # then the whitening filter: every product written into one work array
            term = np.empty((jac.shape[0], 3, *jac.shape[1:3]))  # (b, a, c, L)
            directed = np.multiply(jac[:, None, :, :, 0], rotation[:, 0, :, None, None])
            for j in (1, 2):
                directed += np.multiply(
                    jac[:, None, :, :, j], rotation[:, j, :, None, None], out=term
                )
            filtered = np.zeros((*directed.shape[:3], length + p))
            for i in range(p + 1):  # y(t - i) reads the samples i earlier
                window = filtered[..., p - i : p - i + length]
                window += np.multiply(kernel[:, i, None], directed, out=term)
            gains[lo : lo + 2048] = np.sum(np.square(filtered, out=filtered), axis=3)
        return gains.reshape(n, m, 3, 3)

    @staticmethod
    def _ratio_to_others(energy: np.ndarray) -> np.ndarray:
        """``E_k / mean_{j != k} E_j`` along axis 1 (step 4)."""
        m = energy.shape[1]
        others = (energy.sum(axis=1, keepdims=True) - energy) / (m - 1)
        return energy / others  # type: ignore[no-any-return]

    def _calibrate_residuals(self, body: np.ndarray, reference: np.ndarray) -> None:
        """Whitening filter, residual statistics and energy-ratio threshold (steps 3-5) on
        the whole calibration window."""
        assert self.array is not None and self.mapping is not None and self.network is not None
        length = self.input_length
        windows = input_windows(body, length)  # (W, m, L, 3)
        residual = self._residuals(self._predict(windows), reference[length - 1 :])
        p = self.whiten
        self.window_samples = max(1, round(self.window_s * self.array.rate_hz))
        w = self.window_samples
        if residual.shape[0] - p < 2 * w or residual.shape[0] < 4 * p:
            raise CalibrationError(
                f"cnn-map: {residual.shape[0]} calibration residuals cannot fit an order-{p}"
                f" whitening filter and a {w}-sample energy window; use a longer --calibrate"
                " window"
            )
        # Step 3: AR(p) per component, least squares pooled over IMUs
        self.ar_coefficients = np.stack(
            [fit_autoregression(residual[:, :, c], p) for c in range(3)]
        ).reshape(3, p)
        whitened = whiten(residual, self.ar_coefficients)  # (W - p, m, 3)
        self.residual_mean = whitened.mean(axis=0)  # (m, 3)
        centred = whitened - self.residual_mean
        self.residual_variance = centred.var(axis=0).mean(axis=0)  # (3,) shared by IMUs
        if not np.all(self.residual_variance > 0):
            raise CalibrationError("cnn-map: zero residual variance; check the calibration window")
        squared = (centred**2 / self.residual_variance).mean(axis=2)  # (W - p, m)
        cumulative = np.concatenate([np.zeros((1, squared.shape[1])), np.cumsum(squared, axis=0)])
        energies = (cumulative[w:] - cumulative[:-w]) / w  # (W - p - w + 1, m)
        ratios = self._ratio_to_others(energies)
        # Step 5: gamma law of the pooled energy ratios, Šidák level over the m IMUs
        # (fitting it on the held-out windows alone was tried: 1.5-24 alpha, worse)
        mean = float(ratios.mean())
        self.gamma_shape = gamma_shape(ratios.ravel())
        m = len(self.tested)
        self.imu_level = -math.expm1(math.log1p(-self.mapping_alpha) / m)
        counts = np.arange(1, w + 1, dtype=np.float64)
        shapes = self.gamma_shape * counts / w
        self.thresholds = gamma_distribution.ppf(1.0 - self.imu_level, shapes, scale=mean / shapes)
        self.calibration_alarm_rate = float(np.mean(ratios.max(axis=1) > self.thresholds[-1]))
        self.residual_rms = float(np.sqrt(np.mean(residual**2)))
        self._energy_window = MovingWindow(w, m * 3 + m * 9)
        self._tail = np.zeros((0, m, 3))
        self._residual_tail = np.zeros((0, m, 3))
        self._episode_imu = -1
        self._episode_sums = (np.zeros(3), np.zeros(3))
        self._samples_seen = 0

    def _mapping_block(self, block: ImuBlock) -> DetectionBlock:
        """Steps 1-7 on one block: the mapping test's own output (statistic max_k R_k
        against its threshold, isolation, amplitude, scores); stream state is kept."""
        assert self.network is not None and self.array is not None
        assert block.accel is not None
        n_samples = len(block)
        m = len(self.tested)
        reference = self._reference_rate(block)
        body = self._body_accel(block)
        joined = np.concatenate([self._tail, body], axis=0)
        length = self.input_length
        p = self.whiten
        n_full = joined.shape[0] - length + 1  # windows ending in this block
        # before the first whitened residual: calibrated mean energy, no sensitivity
        squared = np.ones((n_samples, m, 3))
        sensitivity = np.zeros((n_samples, m, 3, 3))
        if n_full > 0:
            windows = input_windows(joined, length)
            residual = self._residuals(self._predict(windows), reference[n_samples - n_full :])
            joined_residual = np.concatenate([self._residual_tail, residual], axis=0)
            n_new = min(joined_residual.shape[0] - p, n_full)
            if n_new > 0:
                whitened = whiten(joined_residual[-(n_new + p) :], self.ar_coefficients)
                squared[n_samples - n_new :] = (
                    whitened - self.residual_mean
                ) ** 2 / self.residual_variance
                gains = self._axis_gains(windows[n_full - n_new :])  # (n_new, m, axis, c)
                # Step 6: S[a, c] = G[a, c] / v_c (energy per added variance)
                sensitivity[n_samples - n_new :] = gains / self.residual_variance
            self._residual_tail = joined_residual[max(0, joined_residual.shape[0] - p) :]
        self._tail = joined[joined.shape[0] - (length - 1) :]
        stacked = np.concatenate(
            [squared.reshape(n_samples, -1), sensitivity.reshape(n_samples, -1)], axis=1
        )
        sums, counts = self._energy_window.push(stacked)
        means = sums / counts[:, None]
        component = means[:, : m * 3].reshape(n_samples, m, 3)  # (N, m, c)
        window_sensitivity = means[:, m * 3 :].reshape(n_samples, m, 3, 3)  # (N, m, a, c)
        ratio = self._ratio_to_others(component.mean(axis=2))  # R_k, (N, m)
        best_imu = np.argmax(ratio, axis=1)
        rows = np.arange(n_samples)
        statistic = ratio[rows, best_imu]
        threshold = self.thresholds[counts - 1]
        alarm = statistic > threshold
        # Step 6: per-axis least-squares fit of the excess component energy ratios
        excess = self._ratio_to_others(component) - 1.0  # (N, m, c)
        projection = np.einsum("nkc,nkac->nka", excess, window_sensitivity)  # x . S_a
        norm2 = np.einsum("nkac,nkac->nka", window_sensitivity, window_sensitivity)
        safe = np.where(norm2 > 0, norm2, 1.0)
        delta = np.where(norm2 > 0, projection / safe, 0.0)  # added variance, (m/s^2)^2
        scores = np.full((n_samples, self.n_accel), np.nan)
        scores[:, self.sensor_of.ravel()] = np.sqrt(np.maximum(delta, 0.0)).reshape(n_samples, -1)
        best_axis = self._episode_axes(
            alarm, best_imu, projection[rows, best_imu], norm2[rows, best_imu]
        )
        return DetectionBlock(
            statistic=statistic,
            threshold=threshold,
            alarm=alarm,
            isolated=np.where(alarm, self.sensor_of[best_imu, best_axis], NO_ISOLATION).astype(
                np.int32
            ),
            amplitude=np.where(alarm, statistic, np.nan),
            scores=scores,
        )

    def _episode_axes(
        self,
        alarm: np.ndarray,
        imu: np.ndarray,
        projection: np.ndarray,
        norm2: np.ndarray,
    ) -> np.ndarray:
        """Accelerometer axis of the isolated IMU from the evidence of the whole alarm
        episode (step 6): ``x . S_a`` and ``|S_a|^2`` are summed over the samples since the
        alarm on this IMU began, and the axis with the best fit ``(sum x.S_a)^2 /
        sum |S_a|^2`` (positive sum) is chosen. State carries over blocks.

        Parameters
        ----------
        alarm : ndarray, shape (N,), bool, N >= 1
        imu : ndarray, shape (N,), int
            Most significant IMU per sample.
        projection, norm2 : ndarray, shape (N, 3)
            ``x . S_a`` and ``|S_a|^2`` of that IMU's axes.

        Returns
        -------
        ndarray, shape (N,), int: axis per sample (meaningful where ``alarm``).
        """
        previous_alarm = np.concatenate([[self._episode_imu >= 0], alarm[:-1]])
        previous_imu = np.concatenate([[self._episode_imu], imu[:-1]])
        starts = alarm & ~(previous_alarm & (previous_imu == imu))
        segment = np.cumsum(starts)  # 0: the episode carried over from the last block
        start_rows = np.flatnonzero(starts)
        sums = []
        for values, carried in (
            (projection, self._episode_sums[0]),
            (norm2, self._episode_sums[1]),
        ):
            masked = np.where(alarm[:, None], values, 0.0)
            cumulative = np.cumsum(masked, axis=0)
            base = np.empty((start_rows.size + 1, 3))
            base[0] = -carried
            base[1:] = np.where(
                (start_rows > 0)[:, None], cumulative[np.maximum(start_rows - 1, 0)], 0.0
            )
            sums.append(cumulative - base[segment])
        total_projection, total_norm2 = sums
        safe = np.where(total_norm2 > 0, total_norm2, 1.0)
        fit = np.where((total_projection > 0) & (total_norm2 > 0), total_projection**2 / safe, 0.0)
        if alarm[-1]:
            self._episode_imu = int(imu[-1])
            self._episode_sums = (total_projection[-1].copy(), total_norm2[-1].copy())
        else:
            self._episode_imu = -1
            self._episode_sums = (np.zeros(3), np.zeros(3))
        return np.argmax(fit, axis=1)  # type: ignore[no-any-return]

    # --- model files and metadata --------------------------------------------------------

    def save_model(self, path: str | Path) -> None:
        """Write the trained network (architecture, standardisation, weights, training
        figures) as an ``.npz`` file reusable with ``model=PATH``.

        Raises
        ------
        DetectorConfigError
            No trained model yet, or the file cannot be written.
        """
        if self.mapping is None:
            raise DetectorConfigError("cnn-map: no model to save; call fit() first")
        try:
            from imufdi_cli.fileio import open_atomic

            with open_atomic(path) as handle:
                handle.write(self.mapping.to_npz_bytes())
        except OSError as err:
            raise DetectorConfigError(f"cnn-map: cannot write model {str(path)!r} ({err})") from err

    def _report_metadata(self) -> dict[str, Any]:
        """Samples and episodes over the mapping test's threshold so far (JSON-ready)."""
        report = self.mapping_report
        ids = self.array.sensor_ids("accel") if self.array is not None else []
        return {
            "samples": report.samples,
            "over_threshold": report.over,
            "rate": report.over / report.samples if report.samples else 0.0,
            "episodes": report.episodes,
            "first_over_sample": report.first_over,
            "max_statistic_over_threshold": report.max_ratio,
            "by_sensor": {ids[k]: v for k, v in sorted(report.by_sensor.items())},
        }
