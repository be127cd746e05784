"""Static int8 quantisation of an ONNX model and its check against the float model
(argmax agreement for classifiers, MAE change for regressors, saturation)."""
from __future__ import annotations

import contextlib
import logging
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from host.data.dataset import atomic_write
from host.learn.onnx_io import model_bytes, run_onnx, is_classifier, session
from host.learn.tasks import (MAX_REGRESSION_CHANGE, MIN_AGREEMENT, QuantisationError,
                              TrainError, check_choice)

__all__ = ["quantise_model", "compare_int8", "int8_saturation"]


@contextlib.contextmanager
def quiet_logging():
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        root.setLevel(level)


def calibration_reader(X: np.ndarray, input_name: str, batch: int = 64):
    """Calibration batches of exactly ``batch`` windows (the histogram calibrators
    need equal shapes): the last, short batch is filled with earlier windows."""
    if len(X) > batch and len(X) % batch:
        X = np.concatenate([X, X[:batch - len(X) % batch]])
    batch = min(batch, len(X))
    from onnxruntime.quantization import CalibrationDataReader

    class _Reader(CalibrationDataReader):
        """Feeds the calibration windows in batches."""

        def __init__(self):
            self._it = iter(range(0, len(X), batch))

        def get_next(self):
            i = next(self._it, None)
            return None if i is None else {input_name: np.ascontiguousarray(
                X[i:i + batch], np.float32)}

        def rewind(self):
            self._it = iter(range(0, len(X), batch))

    return _Reader()


def int8_saturation(float_onnx, int8_onnx, X: np.ndarray) -> dict:
    """Share of the values reaching each quantised activation (run through the float
    model on X) that fall outside the int8 range calibrated for it: the inputs the
    int8 model clips. Returns the overall share, the worst tensor and its share."""
    import onnx
    from onnx import numpy_helper

    q = onnx.load_from_string(model_bytes(int8_onnx))
    init = {i.name: numpy_helper.to_array(i) for i in q.graph.initializer}
    ranges = {}
    for node in q.graph.node:
        if node.op_type != "QuantizeLinear" or node.input[0] in init:
            continue
        scale = float(np.asarray(init[node.input[1]]).reshape(-1)[0])
        zp_arr = init.get(node.input[2]) if len(node.input) > 2 else None
        zp = 0 if zp_arr is None else int(np.asarray(zp_arr).reshape(-1)[0])
        lo_q, hi_q = (-128, 127) if (zp_arr is not None and zp_arr.dtype == np.int8) else (0, 255)
        ranges[node.input[0]] = ((lo_q - zp) * scale - scale / 2, (hi_q - zp) * scale + scale / 2)
    f = onnx.load_from_string(model_bytes(float_onnx))
    known = {o for n in f.graph.node for o in n.output} | {i.name for i in f.graph.input}
    names = [n for n in ranges if n in known]
    if not names or len(X) == 0:
        return {"tensors": 0, "share_outside": 0.0, "worst_tensor": None, "worst_share": 0.0}
    have = {o.name for o in f.graph.output}
    for n in names:
        if n not in have:
            f.graph.output.append(onnx.helper.make_tensor_value_info(n, onnx.TensorProto.FLOAT,
                                                                     None))
    sess = session(f)
    inp = sess.get_inputs()[0].name
    outside = {n: 0 for n in names}
    total = {n: 0 for n in names}
    for i in range(0, len(X), 1024):
        vals = sess.run(names, {inp: np.ascontiguousarray(X[i:i + 1024], np.float32)})
        for n, v in zip(names, vals):
            lo, hi = ranges[n]
            v = np.asarray(v, np.float64)
            outside[n] += int(((v < lo) | (v > hi)).sum())
            total[n] += int(v.size)
    share = {n: outside[n] / total[n] if total[n] else 0.0 for n in names}
    worst = max(names, key=lambda n: share[n])
    return {"tensors": len(names), "share_outside": round(sum(outside.values())
                                                          / max(sum(total.values()), 1), 8),
            "worst_tensor": worst, "worst_share": round(share[worst], 8)}


def compare_int8(float_onnx, int8_onnx, X: np.ndarray, y=None,
                 min_agreement: float = MIN_AGREEMENT,
                 max_regression_change: float = MAX_REGRESSION_CHANGE) -> dict:
    """Int8 against float on windows X (held out): for classifiers the argmax
    agreement, the largest probability difference and (with class ids ``y``) the
    accuracy change; for regressors the largest output difference and (with
    targets ``y``) the MAE change. ``passed`` says whether it meets the bar
    (agreement >= ``min_agreement``; MAE change <= ``max_regression_change`` x the
    target range)."""
    X = np.asarray(X, np.float32)
    if X.ndim < 2 or len(X) == 0:
        raise TrainError(f"compare_int8 needs held-out windows (N, D) or (N, C, H, W), got "
                         f"shape {X.shape}")
    sf, sq = session(model_bytes(float_onnx)), session(model_bytes(int8_onnx))
    pf, pq = run_onnx(sf, X), run_onnx(sq, X)
    if not np.isfinite(pq).all():
        return {"n": int(len(X)), "passed": False, "finite": False,
                "why": "the int8 model gives NaN or inf"}
    if pf.shape != pq.shape:
        return {"n": int(len(X)), "passed": False,
                "why": f"output shapes differ: float {pf.shape}, int8 {pq.shape}"}
    if is_classifier(sf):
        af, aq = pf.argmax(axis=1), pq.argmax(axis=1)
        agree = float((af == aq).mean())
        res = {"n": int(len(X)), "kind": "classifier", "agreement": round(agree, 6),
               "max_prob_diff": round(float(np.abs(pf - pq).max()), 6),
               "min_agreement": min_agreement}
        if y is not None:
            y = np.asarray(y)
            res["accuracy_float"] = round(float((af == y).mean()), 6)
            res["accuracy_int8"] = round(float((aq == y).mean()), 6)
            res["accuracy_change"] = round(res["accuracy_int8"] - res["accuracy_float"], 6)
        res["passed"] = agree >= min_agreement
        return res
    res = {"n": int(len(X)), "kind": "regressor",
           "max_abs_diff": round(float(np.abs(pf - pq).max()), 6)}
    res["passed"] = True
    if y is not None:
        y = np.asarray(y, np.float64)
        mf, mq = float(np.abs(pf - y).mean()), float(np.abs(pq - y).mean())
        rng = float(y.max() - y.min()) if len(y) else 0.0
        res.update({"mae_float": round(mf, 6), "mae_int8": round(mq, 6),
                    "mae_change": round(mq - mf, 6),
                    "mae_change_of_range": round((mq - mf) / rng, 6) if rng > 0 else None})
        res["passed"] = (mq - mf) <= max_regression_change * max(rng, 1e-12)
    return res


def regression_head(float_onnx) -> list[str]:
    """The name of the last MatMul or Gemm of a model (the layer that writes a
    regressor's value), as a list for ``nodes_to_exclude``; empty if it has no name."""
    import onnx

    m = onnx.load_from_string(model_bytes(float_onnx))
    heads = [n.name for n in m.graph.node if n.op_type in ("MatMul", "Gemm")]
    return heads[-1:] if heads and heads[-1] else []


def quantise_model(float_onnx, calibration_inputs, out_path, check_inputs=None,
                   check_targets=None, min_agreement: float = MIN_AGREEMENT,
                   calibrate_method: str = "minmax", per_channel: bool = True) -> dict:
    """Static int8 quantisation (QDQ, uint8 activations, int8 weights) of the
    MatMuls, Gemms and Convs of ``float_onnx`` (a path, bytes or ModelProto),
    calibrated on ``calibration_inputs`` training windows (N, D), or (N, T, H, W)
    frame stacks for the CNN; writes ``out_path``.

    Then checks the int8 model against the float one on ``check_inputs`` (held-out
    windows; default: the calibration windows) with :func:`compare_int8`, and
    measures int8 saturation (:func:`int8_saturation`) on both sets. When the check
    fails, ``out_path`` is removed and :class:`QuantisationError` raised. Returns the
    report (agreement, largest probability difference or regression error change,
    saturation, sizes).
    """
    from onnxruntime.quantization import (CalibrationMethod, QuantFormat, QuantType,
                                          quantize_static)

    methods = {"minmax": CalibrationMethod.MinMax, "percentile": CalibrationMethod.Percentile,
               "entropy": CalibrationMethod.Entropy}
    check_choice("calibrate_method", calibrate_method, tuple(methods))
    Xc = np.asarray(calibration_inputs, np.float32)
    if Xc.ndim < 2 or len(Xc) == 0:
        raise TrainError(f"calibration_inputs must be windows (N, D) or (N, C, H, W) with "
                         f"N >= 1, got shape {Xc.shape}")
    if not np.isfinite(Xc).all():
        raise TrainError("calibration_inputs hold NaN or inf; encode them with "
                         "device.pi.models.window")
    fbytes = model_bytes(float_onnx)
    out_path = Path(out_path)
    sess = session(fbytes)
    input_name = sess.get_inputs()[0].name
    # a regressor's head stays float: its weights map straight onto the physical value,
    # and an int8 head with large, cancelling weights moved a small fnn's MAE by 5 % of
    # the target range (0.02 with the head in float)
    keep_float = [] if is_classifier(sess) else regression_head(fbytes)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="tacfoot-q-") as tmp:
        fpath = Path(tmp) / "float.onnx"
        fpath.write_bytes(fbytes)
        qpath = Path(tmp) / "int8.onnx"
        with quiet_logging():
            quantize_static(str(fpath), str(qpath), calibration_reader(Xc, input_name),
                            quant_format=QuantFormat.QDQ, activation_type=QuantType.QUInt8,
                            weight_type=QuantType.QInt8, per_channel=per_channel,
                            op_types_to_quantize=["MatMul", "Gemm", "Conv"],
                            nodes_to_exclude=keep_float,
                            calibrate_method=methods[calibrate_method])
        qbytes = qpath.read_bytes()
    quant_s = time.perf_counter() - t0
    Xh = Xc if check_inputs is None else np.asarray(check_inputs, np.float32)
    report = compare_int8(fbytes, qbytes, Xh, check_targets, min_agreement=min_agreement)
    report["checked_on"] = "calibration windows" if check_inputs is None else "held-out windows"
    report["saturation"] = {"calibration": int8_saturation(fbytes, qbytes, Xc),
                            "test": int8_saturation(fbytes, qbytes, Xh)}
    report.update({"calibration_windows": int(len(Xc)), "calibrate_method": calibrate_method,
                   "format": "QDQ u8 activations / s8 weights" + (" per channel"
                                                                   if per_channel else ""),
                   "float_bytes": len(fbytes), "int8_bytes": len(qbytes),
                   "quantise_s": round(quant_s, 3)})
    if not report["passed"]:
        with contextlib.suppress(FileNotFoundError):
            out_path.unlink()
        if report.get("kind") == "classifier":
            why = (f"agrees with the float model on {report['agreement']:.2%} of "
                   f"{report['n']} {report['checked_on']} (argmax), below the required "
                   f"{min_agreement:.2%}; largest probability difference "
                   f"{report['max_prob_diff']:.3f}")
        elif "why" in report:
            why = report["why"]
        else:
            why = (f"raises the MAE by {report.get('mae_change')} "
                   f"({report.get('mae_change_of_range')} of the target range), more than "
                   f"{MAX_REGRESSION_CHANGE:.0%}")
        raise QuantisationError(f"int8 check failed: {out_path} {why}; the int8 model was "
                                f"not kept (ship the float model, or calibrate on more "
                                f"windows)", kind=report.get("kind"),
                                agreement=report.get("agreement"),
                                required=min_agreement if report.get("kind") == "classifier"
                                else None,
                                mae_change=report.get("mae_change"),
                                mae_change_of_range=report.get("mae_change_of_range"),
                                path=str(out_path))
    out_path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out_path, lambda fh: fh.write(qbytes))
    report["path"] = str(out_path)
    return report

