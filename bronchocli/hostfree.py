"""Float64 arithmetic that gives the same bits on every host: the pose-producing code's only maths.

NumPy and the C library choose their kernels by CPU at run time, and the kernels round differently:
``np.arctan2``/``np.arccos``/``np.exp``/``np.log``/``np.power`` take AVX-512 (SVML) code paths where the CPU
has them, ``np.sin``/``np.cos`` and ``math.*`` call glibc, which picks FMA or SSE2 variants, and
``np.dot``/``@``/``np.linalg.norm`` of a vector call OpenBLAS, whose kernel (Haswell, SkylakeX, Zen, ...)
is picked from the CPU. Each gives results that differ in the last bits between hosts (measured:
docs/reproduction.md, "One seed, one dataset"). In dataset generation a last-bit difference does not stay
there: an "inside the lumen?" test on a camera proposal can flip, the random walk then draws other numbers,
and the whole rest of a trajectory differs.

Every function here is built only from operations IEEE 754 rounds exactly one way on every CPU (``+``,
``-``, ``*``, ``/``, ``sqrt``, ``rint``, ``frexp``/``ldexp``, ``copysign``, comparisons), each a separate
NumPy ufunc call (so no compiler can fuse a multiply and an add), in a fixed order. The elementary
functions are fdlibm's algorithms (Sun Microsystems, 1993: argument reduction and minimax polynomials),
accurate to about 1 ulp for the arguments used here (angles of a few turns; ``exp``/``log`` over the normal
range). Inputs are arrays or scalars; scalars give NumPy float64 scalars.
"""

from __future__ import annotations

import numpy as np

PI = 3.14159265358979311600e+00
PI_LO = 1.22464679914735317720e-16
HALF_PI = 1.57079632679489655800e+00

# sin/cos: Cody-Waite reduction by pi/2 (first 33 bits + the rest), then fdlibm's __kernel_sin/__kernel_cos
_INV_PIO2 = 6.36619772367581382433e-01
_PIO2_1 = 1.57079632673412561417e+00
_PIO2_1T = 6.07710050650619224932e-11
_S = (-1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04,
      2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10)
_C = (4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05,
      -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11)
# atan: fdlibm's s_atan.c
_ATAN_HI = (4.63647609000806093515e-01, 7.85398163397448278999e-01, 9.82793723247329054082e-01, HALF_PI)
_ATAN_LO = (2.26987774529616870924e-17, 3.06161699786838301793e-17, 1.39033110312309984516e-17,
            6.12323399573676603587e-17)
_AT = (3.33333333333329318027e-01, -1.99999999998764832476e-01, 1.42857142725034663711e-01,
       -1.11111104054623557880e-01, 9.09088713343650656196e-02, -7.69187620504482999495e-02,
       6.66107313738753120669e-02, -5.83357013379057348645e-02, 4.97687799461593236017e-02,
       -3.65315727442169155270e-02, 1.62858201153657823623e-02)
# exp and log: fdlibm's e_exp.c and e_log.c
_LN2_HI, _LN2_LO, _INV_LN2 = 6.93147180369123816490e-01, 1.90821492927058770002e-10, 1.44269504088896338700e+00
_P = (1.66666666666666019037e-01, -2.77777777770155933842e-03, 6.61375632143793436117e-05,
      -1.65339022054652515390e-06, 4.13813679705723846039e-08)
_LG = (6.666666666666735130e-01, 3.999999999940941908e-01, 2.857142874366239149e-01, 2.222219843214978396e-01,
       1.818357216161805012e-01, 1.531383769920937332e-01, 1.479819860511658591e-01)
_SQRT_HALF = 7.07106781186547524401e-01


def _f64(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def _out(x: np.ndarray):
    return x[()] if x.ndim == 0 else x


def _poly(z, coefs) -> np.ndarray:
    """coefs[0] + z * (coefs[1] + z * (...)), Horner's scheme in this order."""
    acc = np.full_like(z, coefs[-1])
    for c in coefs[-2::-1]:
        acc = acc * z + c
    return acc


# -- vectors and matrices (no BLAS) ---------------------------------------------------------------------


def dot(a, b):
    """Sum over the last axis of ``a * b``, added left to right (``np.dot``/``@`` of vectors without BLAS)."""
    a, b = _f64(a), _f64(b)
    acc = a[..., 0] * b[..., 0]
    for i in range(1, max(a.shape[-1], b.shape[-1])):
        acc = acc + a[..., i] * b[..., i]
    return _out(acc)


def norm(v):
    """Euclidean norm over the last axis."""
    return _out(np.sqrt(_f64(dot(v, v))))


def unit(v) -> np.ndarray:
    """``v`` divided by its norm over the last axis."""
    v = _f64(v)
    return v / _f64(norm(v))[..., None]


def matmul(a, b) -> np.ndarray:
    """``a @ b`` for stacks of matrices ``(..., n, k) @ (..., k, m)``, each entry summed over k in order."""
    a, b = _f64(a), _f64(b)
    acc = a[..., :, 0, None] * b[..., None, 0, :]
    for j in range(1, a.shape[-1]):
        acc = acc + a[..., :, j, None] * b[..., None, j, :]
    return acc


def matvec(a, v) -> np.ndarray:
    """``a @ v`` for stacks of matrices ``(..., n, k)`` and vectors ``(..., k)``."""
    return matmul(a, _f64(v)[..., :, None])[..., 0]


# -- elementary functions -----------------------------------------------------------------------------


def _reduce(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(r, quadrant) with x = quadrant * pi/2 + r, |r| <= pi/4 (accurate for |x| < 2**20 * pi/2)."""
    n = np.rint(x * _INV_PIO2)
    r = (x - n * _PIO2_1) - n * _PIO2_1T
    return r, np.mod(n, 4.0)


def _ksin(r: np.ndarray) -> np.ndarray:
    z = r * r
    return r + (r * z) * (_S[0] + z * _poly(z, _S[1:]))


def _kcos(r: np.ndarray) -> np.ndarray:
    z = r * r
    hz = 0.5 * z
    w = 1.0 - hz
    return w + (((1.0 - w) - hz) + (z * z) * _poly(z, _C))


def sin(x):
    x = _f64(x)
    r, q = _reduce(x)
    s, c = _ksin(r), _kcos(r)
    out = np.select([q == 0.0, q == 1.0, q == 2.0], [s, c, -s], -c)
    return _out(np.where(x == 0.0, x, out))  # keeps the sign of a zero


def cos(x):
    x = _f64(x)
    r, q = _reduce(x)
    s, c = _ksin(r), _kcos(r)
    return _out(np.select([q == 0.0, q == 1.0, q == 2.0], [c, -s, -c], s))


def atan(x):
    x = _f64(x)
    a = np.abs(x)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ids = np.select([a < 0.4375, a < 0.6875, a < 1.1875, a < 2.4375], [-1, 0, 1, 2], 3)
        red = np.select([ids == -1, ids == 0, ids == 1, ids == 2],
                        [a, (2.0 * a - 1.0) / (2.0 + a), (a - 1.0) / (a + 1.0), (a - 1.5) / (1.0 + 1.5 * a)], -1.0 / a)
    z = red * red
    w = z * z
    s1 = z * _poly(w, _AT[0::2])
    s2 = w * _poly(w, _AT[1::2])
    small = red - red * (s1 + s2)
    hi, lo = np.asarray(_ATAN_HI)[np.maximum(ids, 0)], np.asarray(_ATAN_LO)[np.maximum(ids, 0)]
    big = hi - ((red * (s1 + s2) - lo) - red)
    return _out(np.copysign(np.where(ids < 0, small, big), x))


def atan2(y, x):
    """IEEE ``atan2`` (signed zeros included) for finite arguments."""
    y, x = np.broadcast_arrays(_f64(y), _f64(x))
    with np.errstate(divide="ignore", invalid="ignore"):
        z = _f64(atan(np.abs(y / x)))
    neg_x = np.signbit(x)
    mag = np.where(neg_x, PI - (z - PI_LO), z)
    mag = np.where(x == 0.0, np.where(y == 0.0, np.where(neg_x, PI, 0.0), HALF_PI), mag)
    return _out(np.copysign(mag, y))


def acos(x):
    """arccos on [-1, 1] (NaN outside), as atan2(sqrt(1 - x²), x)."""
    x = _f64(x)
    with np.errstate(invalid="ignore"):
        return atan2(np.sqrt((1.0 - x) * (1.0 + x)), x)


def exp(x):
    x = _f64(x)
    k = np.rint(x * _INV_LN2)
    hi = x - k * _LN2_HI
    lo = k * _LN2_LO
    r = hi - lo
    t = r * r
    c = r - t * _poly(t, _P)
    y = 1.0 - ((lo - (r * c) / (2.0 - c)) - hi)
    with np.errstate(over="ignore"):
        return _out(np.ldexp(y, np.clip(k, -2000, 2000).astype(np.int64)))


def log(x):
    """Natural logarithm for x > 0 (-inf at 0, NaN below)."""
    x = _f64(x)
    m, e = np.frexp(x)
    low = m < _SQRT_HALF
    m = np.where(low, m * 2.0, m)
    k = (e - low).astype(np.float64)
    f = m - 1.0
    with np.errstate(divide="ignore", invalid="ignore"):  # x <= 0: replaced below
        s = f / (2.0 + f)
    z = s * s
    w = z * z
    r = z * _poly(w, _LG[0::2]) + w * _poly(w, _LG[1::2])
    hfsq = 0.5 * f * f
    out = k * _LN2_HI - ((hfsq - (s * (hfsq + r) + k * _LN2_LO)) - f)
    return _out(np.where(x > 0.0, out, np.where(x == 0.0, -np.inf, np.nan)))


def power(x, y):
    """``x ** y`` for x > 0, as exp(y log x)."""
    return exp(_f64(y) * _f64(log(x)))
