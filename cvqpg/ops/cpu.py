"""What the ops' CPU kernels (Numba) share: the options of the functions that only kernels call, and
the helpers that kernels of more than one op compile in. Kernel modules import them from here, so
that each lives in one file."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

# Numba options for the CPU kernels' functions that only other kernels call: without the CPython and C
# wrappers that Numba otherwise compiles for every function, which nothing calls. Their machine code is
# the same and a cold compile takes less CPU time (docs/performance.md, "First run"). Python cannot call
# such a function.
CALLED_BY_KERNELS_ONLY = {"no_cpython_wrapper": True, "no_cfunc_wrapper": True}


# π/2 in three parts (the first two with trailing zero bits), and the Taylor-minimax coefficients of
# sin and cos on [−π/4, π/4] that fdlibm uses.
HALF_PI_PARTS = (1.57079632673412561417e+00, 6.07710050630396597660e-11, 2.02226624879595063154e-21)
SIN_COEFFICIENTS = (-1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04,
                    2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10)
COS_COEFFICIENTS = (4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05,
                    -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11)


@nb.njit(cache=True, nogil=True, fastmath={"contract"})
def cosines_and_sines(angles, cosines, sines):
    """cos and sin of every angle (rad, |angle| ≲ 1e5) to about 1e-16 relative, in a branch-free loop
    that LLVM vectorises, where libm's sin and cos are a call per value and each primitive needs six
    per channel (docs/performance.md, "Measured choices"). The angle is reduced by the nearest
    multiple n of π/2 (three-part π/2, exact products by fused multiply-adds; no reassociation allowed
    here), the polynomials are taken at the remainder, and n mod 4 swaps them and sets their signs."""
    p1, p2, p3 = HALF_PI_PARTS
    s1, s2, s3, s4, s5, s6 = SIN_COEFFICIENTS
    c1, c2, c3, c4, c5, c6 = COS_COEFFICIENTS
    for i in range(angles.shape[0]):
        n = np.floor(angles[i] * (2.0 / math.pi) + 0.5)
        r = ((angles[i] - n * p1) - n * p2) - n * p3
        z = r * r
        sine = r + r * z * (s1 + z * (s2 + z * (s3 + z * (s4 + z * (s5 + z * s6)))))
        cosine = 1.0 - 0.5 * z + z * z * (c1 + z * (c2 + z * (c3 + z * (c4 + z * (c5 + z * c6)))))
        quadrant = n - 4.0 * np.floor(0.25 * n)  # 0 to 3: (sin, cos) is (s, c), (c, −s), (−s, −c), (−c, s)
        odd = quadrant - 2.0 * np.floor(0.5 * quadrant)
        after = quadrant + 1.0 - 4.0 * np.floor(0.25 * (quadrant + 1.0))
        sines[i] = ((1.0 - odd) * sine + odd * cosine) * (1.0 - 2.0 * np.floor(0.5 * quadrant))
        cosines[i] = ((1.0 - odd) * cosine + odd * sine) * (1.0 - 2.0 * np.floor(0.5 * after))
