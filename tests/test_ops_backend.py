"""`--backend torch` runs PyTorch only: a whole CPU fit with it calls no Numba-compiled function, and its
targets' noise is the Numba kernel's, drawn by the PyTorch reference."""

import subprocess
import sys

import numpy as np
import pytest
import torch

from cvqpg.ops.loss import cpu as loss_kernels, reference, standard_normal

# A fresh process in which every Numba-compiled function that is called, or compiled from types, is
# recorded before it runs: a dispatcher's first call in a process passes through `_compile_for_args` and
# `compile`, whether it compiles or loads from the cache. It runs `cvqpg fit` with the backend given
# and prints the exit code and the record.
RECORDED_FIT = """
import sys
from numba.core.dispatcher import Dispatcher

record = set()
for name in ("_compile_for_args", "compile"):
    def recorded(self, *args, _run=getattr(Dispatcher, name), **kwargs):
        record.add(f"{self.py_func.__module__}.{self.py_func.__qualname__}")
        return _run(self, *args, **kwargs)
    setattr(Dispatcher, name, recorded)

from cvqpg.cli import main
code = main(["fit", "--size", "32", "24", "--num-gaussians", "20", "--steps", "3", "--backend", sys.argv[1],
             "--out", sys.argv[2], "--quiet"])
print(code, sorted(record))
"""


def numba_functions_called_by_a_fit(backend: str, out) -> str:
    done = subprocess.run([sys.executable, "-c", RECORDED_FIT, backend, str(out)], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    code, _, record = done.stdout.strip().splitlines()[-1].partition(" ")
    assert code == "0", done.stdout
    return record


@pytest.mark.slow
def test_a_cpu_fit_with_the_torch_backend_calls_no_numba_function(tmp_path):
    assert numba_functions_called_by_a_fit("torch", tmp_path / "torch") == "[]"
    # the record sees the kernels where they run
    assert "cvqpg.ops.rasterize.cpu.splat_forward" in numba_functions_called_by_a_fit("numba", tmp_path / "numba")


@pytest.mark.parametrize("seed", [0, 7, 2**63 - 2])
def test_the_noise_kernel_draws_the_reference_s_numbers(seed):
    """`cpu.standard_normals` against its PyTorch reference: the same counter-based draws, within 4 units
    in the last place (the kernel's vectorised ln, cos and sin against PyTorch's). How many are bit-identical
    depends on the CPU's vector maths: about 76% on an AMD EPYC, more on an Intel Xeon."""
    kernel = torch.empty(100_002)
    loss_kernels.standard_normals(seed, kernel.numpy())
    drawn = reference.standard_normals(seed, kernel.numel())
    assert drawn.dtype == torch.float32 and drawn.shape == kernel.shape
    assert torch.equal(torch.sign(drawn), torch.sign(kernel)) and float(drawn.abs().max()) < 5.8
    ulps = np.abs(drawn.numpy().view(np.int32).astype(np.int64) - kernel.numpy().view(np.int32).astype(np.int64))
    assert ulps.max() <= 4 and (ulps == 0).mean() > 0.6


def test_the_backend_picks_the_noise_s_kernel_or_its_reference_from_the_same_seed():
    shape = (2, 3, 5, 7)
    draws = {backend: standard_normal(shape, torch.Generator().manual_seed(3), backend)
             for backend in ("numba", "torch")}
    assert torch.equal(draws["numba"], standard_normal(shape, torch.Generator().manual_seed(3)))  # auto, on the CPU
    assert draws["torch"].shape == shape
    torch.testing.assert_close(draws["torch"], draws["numba"], rtol=1e-6, atol=1e-6)
