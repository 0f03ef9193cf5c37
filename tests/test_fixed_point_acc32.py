"""int32 accumulators (blob version 3, ``fbg_layer.acc32``): the exporter's proof, the loader's
re-proof (C and Python), the integer reference, and the precision trade (docs/fixed-point.md,
"int32 layers")."""
from __future__ import annotations

import json
import shutil
import struct
import zlib

import numpy as np
import pytest

from fbgforce.errors import InputError
from fbgforce.export import blob, intref
from fbgforce.export import quantize as qz
from fbgforce.export.qmodel import NET_NAMES, QLayer, QModel
from fbgforce.export.exporter import export_model
from fbgforce.pybind import ffi, lib

INT32_MAX = 2**31 - 1


def _load_c(data: bytes) -> int:
    buf = ffi.new("uint64_t[]", (len(data) + 15) // 8)
    ffi.memmove(buf, data, len(data))
    return lib.fbg_model_from_blob(ffi.new("fbg_model *"), ffi.cast("uint8_t *", buf), len(data))


def _recrc(data: bytearray) -> bytes:
    total = struct.unpack_from("<I", data, 8)[0]
    struct.pack_into("<I", data, 12, zlib.crc32(bytes(data[16:total])) & 0xFFFFFFFF)
    return bytes(data)


def _entry_offsets(q: QModel) -> list[tuple[int, int, int]]:
    """(net, layer, byte offset of its layer-table entry)."""
    out, off = [], blob.PARAMS_END
    for n, net in enumerate(q.nets):
        for i in range(len(net)):
            out.append((n, i, off))
            off += blob.LAYER_ENTRY.size
    return out


def _bound32(w: np.ndarray, b: np.ndarray, relu_inputs: bool) -> np.ndarray:
    """The int32 proof recomputed here from the integers, independently of quantize.py."""
    w = w.astype(object)
    if relu_inputs:
        s = np.maximum(np.where(w > 0, w, 0).sum(axis=1), np.where(w < 0, -w, 0).sum(axis=1))
    else:
        s = np.abs(w).sum(axis=1)
    return s * 32767 + np.abs(b.astype(object))


@pytest.fixture(scope="module")
def int64_dir(tmp_path_factory, small_model_dir):
    """The small model exported the blob-version-2 way: int64 everywhere."""
    out = tmp_path_factory.mktemp("acc64") / "model"
    shutil.copytree(small_model_dir, out)
    export_model(out, onnx=False, acc32_max_drop=-1.0)
    return out


def test_default_export_proves_every_int32_layer(small_exported_dir):
    q = blob.load_model_blob(small_exported_dir)
    report = json.loads((small_exported_dir / "export_report.json").read_text())
    n32 = 0
    for name, net in zip(NET_NAMES, q.nets):
        for i, ly in enumerate(net):
            info = report["nets"][name][i]
            assert info["acc32"] == ly.acc32
            if ly.acc32:
                n32 += 1
                bound = int(_bound32(ly.w, ly.bias, i > 0).max())
                assert bound <= INT32_MAX and bound == info["acc32_bound"]
                assert ly.shift <= 32
                assert 0.0 <= info["acc32_weight_bits_dropped"] <= qz.ACC32_MAX_DROP
    # The later layers hold nearly all MACs: they must be the int32 ones on this model.
    assert all(ly.acc32 for net in q.nets for ly in net[1:])
    assert n32 >= 9
    # Generated C carries the same flags.
    src = next((small_exported_dir / "c").glob("*_model.c")).read_text()
    assert src.count("/* acc32 */ 1") == n32


def test_int32_costs_little_accuracy(small_exported_dir, int64_dir):
    """Same model, same calibration data: fixed vs float errors of the int32 export stay in
    the task's aim (0.05 N, 0.05 mm) and near the int64 export's."""
    r32 = json.loads((small_exported_dir / "export_report.json").read_text())["calibration_check"]
    r64 = json.loads((int64_dir / "export_report.json").read_text())["calibration_check"]
    for k in ("max_abs_err_force_N", "max_abs_err_x_mm", "max_abs_err_y_mm"):
        assert r32[k] <= 0.05, (k, r32[k], r64[k])
        assert r32[k] <= 2.0 * r64[k] + 0.005, (k, r32[k], r64[k])
    assert not any(ly.acc32 for net in blob.load_model_blob(int64_dir).nets for ly in net)


def test_loader_refuses_an_unproven_int32_flag(int64_dir):
    """Flag an int64 layer whose bound exceeds int32 as acc32: C says FBG_ERR_BOUND and the
    Python parser refuses it too; bad flag bytes are FBG_ERR_RANGE."""
    data = (int64_dir / "model.fbgm").read_bytes()
    q = blob.from_bytes(data)
    assert _load_c(data) == lib.FBG_OK
    hit = 0
    for n, i, off in _entry_offsets(q):
        ly = q.nets[n][i]
        if int(_bound32(ly.w, ly.bias, i > 0).max()) <= INT32_MAX:
            continue
        bad = bytearray(data)
        bad[off + 6] = 1
        bad = _recrc(bad)
        assert _load_c(bad) == lib.FBG_ERR_BOUND, (n, i)
        with pytest.raises(InputError, match="int32"):
            blob.from_bytes(bad)
        hit += 1
    assert hit >= 3
    _, _, off = _entry_offsets(q)[1]
    for pos, val in ((off + 6, 2), (off + 7, 1)):
        bad = bytearray(data)
        bad[pos] = val
        assert _load_c(_recrc(bad)) == lib.FBG_ERR_RANGE
        with pytest.raises(InputError, match="layer table"):
            blob.from_bytes(_recrc(bytearray(bad)))


def test_relu_input_rule_applies_only_after_a_nets_first_layer(small_exported_dir, monkeypatch):
    """A row [a, a, -a, -a] with a = 32767: any int16 inputs reach 4 a 32767 > INT32_MAX, inputs
    in [0, 32767] at most 2 a 32767 <= INT32_MAX. As a first layer (signed z inputs) the C
    loader must refuse it as int32; after a ReLU it must accept it."""
    q = blob.load_model_blob(small_exported_dir)
    row = np.array([32767, 32767, -32767, -32767])
    monkeypatch.setattr(QModel, "check", lambda self: None)  # write what the exporter never would
    first = q.nets[0][0]
    first.w = first.w.copy()
    first.w[0] = 0
    first.w[0, :4] = row
    first.bias = first.bias.copy()
    first.bias[0] = 0
    first.acc32 = True
    assert _load_c(blob.to_bytes(q)) == lib.FBG_ERR_BOUND
    q = blob.load_model_blob(small_exported_dir)
    second = q.nets[0][1]
    second.w = second.w.copy()
    second.w[0] = 0
    second.w[0, :4] = row
    second.bias = second.bias.copy()
    second.bias[0] = 0
    second.acc32 = True
    data = blob.to_bytes(q)
    monkeypatch.undo()
    assert _load_c(data) == lib.FBG_OK
    blob.from_bytes(data)  # the Python check agrees


def test_intref_sums_int32_only_with_the_proof():
    w = np.array([[32767, 32767, -32767, -32767]])
    ly = QLayer(w, 16, [0], [1 << 20], 32, acc32=True)
    x_pos = np.array([[32767, 32767, 0, 0]])
    assert intref._acc(ly, x_pos, True)[0, 0] == 2 * 32767 * 32767
    with pytest.raises(ValueError, match="proof"):
        intref._acc(ly, np.array([[32767, 32767, -32767, -32767]]), False)
    with pytest.raises(ValueError, match="proof"):
        intref._acc(ly, np.array([[32767, 0, -1, 0]]), True)


def test_acc32_scale_meets_the_bound_with_rounding():
    """_acc32_scale's slack covers the rounding of every weight and bias (worst-case rows)."""
    rng = np.random.default_rng(1)
    for relu in (False, True):
        for n in (4, 6, 20, 70, 128):
            w = rng.normal(size=(40, n))
            w[0] = np.abs(w[0])        # one-signed row: the ReLU rule gains nothing there
            b = rng.normal(size=40) * 3.0
            in_scale = 1e-4
            base = np.abs(w).max(axis=1) / 32767
            s = qz._acc32_scale(w, b, in_scale, base, relu)
            wq, bq, _, bound32 = qz._int_weights(w, b, in_scale, s, 32767, relu)
            assert bound32.max() <= INT32_MAX
            assert bound32.max() > INT32_MAX * 0.99  # and it does not waste resolution


def test_state_activations_are_8_byte_aligned():
    assert ffi.offsetof("fbg_state", "act") % 8 == 0
