"""The compiled kernels: one signature each, warmed in the background on a fresh install
(compilation must not make a fresh install's first run much slower).

* Whatever arrays a caller passes (read-only columns, strided views, other dtypes), each kernel
  is compiled for the one signature registered in :data:`tertiary.core.jit.KERNELS`. Oracle:
  numba's own list of the dispatcher's compiled signatures.
* :func:`tertiary.pipeline.warmup.warm_kernels` compiles a kernel into numba's cache in another
  process, and the run's first call then loads it instead of compiling. Oracle: numba's cache
  statistics, in a fresh process with an empty cache directory.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np

from tertiary.core import jit
from tertiary.evaluation.bound import BoundConfig, _pcrb_block
from tertiary.pipeline import warmup
from tertiary.stages.tracking.altitude import AltitudeConfig, FilterCarry, filter_tracks_carry
from tertiary.filters import make_filter


def _read_only(a: np.ndarray) -> np.ndarray:
    a = np.array(a)
    a.flags.writeable = False        # what a polars column gives through to_numpy()
    return a


def test_each_kernel_is_compiled_for_its_one_declared_signature():
    rng = np.random.default_rng(3)
    n = 40
    t = np.sort(rng.uniform(0.0, 200.0, n))
    z = 3000.0 + rng.normal(0.0, 20.0, n)
    var = np.full(n, 400.0)
    starts, lengths = np.array([0, 20]), np.array([20, 20])
    # read-only, strided and int32/float32 inputs: each used to be (or would be) a signature of its own
    filter_tracks_carry(_read_only(t), np.repeat(z, 2)[::2], var.astype(np.float32), starts.astype(np.int32),
                        _read_only(lengths), AltitudeConfig(), ident=_read_only(np.arange(n) // 20))
    _, _, _, carry = filter_tracks_carry(t, z, var, starts, lengths, AltitudeConfig())
    # a carried state in another memory layout (F-ordered, strided), as a later window's state
    # read back from a frame can be: CI once compiled two more signatures from it
    carry = FilterCarry(*(np.asfortranarray(a) if a.ndim > 1 else a[::-1][::-1] for a in (
        carry.models, carry.mu, carry.t_last, carry.ok, carry.conf, carry.miss, carry.last_id,
        carry.post, carry.has, carry.held, carry.held_id)))
    filter_tracks_carry(t + 300.0, z, var, starts, lengths, AltitudeConfig(), init=carry)
    flt = make_filter("imm_sym")
    b = 3
    st = flt.init(rng.normal(0.0, 1e3, (b, 3)), np.tile(np.diag([100.0, 100.0, 400.0]), (b, 1, 1)))
    st = {k: _read_only(v) for k, v in st.items()}
    pred = flt.predict(st, _read_only(np.full(b, 4.0)))
    flt.update(pred, _read_only(rng.normal(0.0, 1e3, (b, 3))), np.tile(np.diag([100.0, 100.0, 400.0]), (b, 1, 1)),
               _read_only(np.ones(b, bool)))
    flt.observe_velocity(pred, _read_only(rng.normal(0.0, 100.0, (b, 2))), _read_only(np.tile(np.eye(2), (b, 1, 1))),
                         _read_only(np.ones(b, bool)))
    flt.output(pred)
    # the bound's recursion, from a read-only truth-time column and a strided record mask
    r_eq = np.full((n, 3, 3), np.nan)
    r_eq[::3] = np.diag([2500.0, 2500.0, 1e4])
    _pcrb_block(_read_only(t), r_eq, _read_only(starts), lengths.astype(np.int32), np.ones(2 * n, bool)[::2],
                BoundConfig())
    assert set(warmup.GROUPS[0] + warmup.GROUPS[1]) <= set(jit.KERNELS)
    for name, k in jit.KERNELS.items():
        if k.module.startswith("tertiary.simulate"):     # the simulator's, not a run's
            continue
        assert [tuple(s) for s in k.dispatcher.signatures] == [tuple(k.signature())], name


def test_warm_compiles_into_the_cache_and_the_first_call_loads_it(tmp_path):
    script = textwrap.dedent("""
        import numpy as np
        from tertiary.core import jit
        from tertiary.pipeline.warmup import warm_kernels
        from tertiary.stages.tracking.altitude import AltitudeConfig, filter_tracks_carry
        from tertiary.stages.tracking.altitude_kernel import filter_recursion
        assert not jit.is_cached("altitude")
        assert warm_kernels(["altitude"]) == ["altitude"]
        assert warm_kernels(["altitude"]) == []          # one compilation, not two
        jit.ready_for("altitude")
        assert jit.is_cached("altitude")
        t = np.arange(10.0)
        filter_tracks_carry(t, 1000.0 + t, np.full(10, 100.0), np.array([0]), np.array([10]), AltitudeConfig())
        stats = filter_recursion.stats
        assert sum(stats.cache_hits.values()) == 1 and not stats.cache_misses, stats
        print("ok")
    """)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]
    assert any((tmp_path / "numba").rglob("*filter_recursion*.nbc"))


def test_a_kernel_is_ready_when_it_is_cached_not_when_its_group_is(tmp_path):
    """The tracker's kernels and the bound's are compiled in one background process, in that
    order: the tracker's wait ends when its own kernels are in the cache, while the process is
    still compiling the bound's. Oracle: numba's cache index and the process's state."""
    script = textwrap.dedent("""
        from tertiary.core import jit
        from tertiary.pipeline.warmup import warm_kernels
        names = ["imm_predict", "imm_update", "pcrb"]
        assert warm_kernels(names) == names
        job = jit.job("pcrb")
        jit.ready_for("imm_predict")
        jit.ready_for("imm_update")
        assert jit.is_cached("imm_update") and job.poll() is None     # the bound's still compiling
        jit.ready_for("pcrb")
        assert jit.is_cached("pcrb")
        print("ok")
    """)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def test_a_run_warms_only_the_kernels_its_filters_call():
    assert warmup.kernels_for(()) == ["altitude"]
    assert warmup.kernels_for(("singer",)) == ["altitude"]
    assert warmup.kernels_for(("singer", "imm_sym")) == ["altitude", "imm_predict", "imm_output", "imm_update",
                                                           "imm_velocity"]
    assert warmup.kernels_for(("no-such-filter",)) == ["altitude"]
    assert warmup.kernels_for(("singer",), bound=True) == ["altitude", "pcrb"]


def test_nothing_is_warmed_when_numba_compiles_nothing():
    """NUMBA_DISABLE_JIT (a debugging switch) leaves plain functions: no background process, no error."""
    script = ("from tertiary.core import jit\n"
              "from tertiary.pipeline.warmup import warm_kernels\n"
              "assert all(jit.is_cached(n) for n in jit.KERNELS)\n"
              "assert warm_kernels(list(jit.KERNELS)) == []\n"
              "print('ok')\n")
    out = subprocess.run([sys.executable, "-c", script], env=dict(os.environ, NUMBA_DISABLE_JIT="1"),
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]
