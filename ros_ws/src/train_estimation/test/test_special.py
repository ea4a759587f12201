"""numerics.special is scipy.special's own functions, and diagnose's imports do not import the
scipy.special package (its array-API set-up, 0.15-0.19 s of CPU at a process's start)."""

import subprocess
import sys

import numpy as np


def test_diagnose_imports_no_scipy_special():
    code = ("import sys\n"
            "import train_estimation.tools.diagnose, train_estimation.core.offline.diagnose\n"
            "from train_estimation.core.numerics import special\n"
            "print(sorted(m for m in sys.modules if m == 'scipy.special' or "
            "m.startswith(('scipy._lib._array_api', 'scipy.special._support'))))\n"
            "print(special._U.__file__)\n"
            # scipy.special imported after it works as ever, on the same compiled functions
            "import scipy.special as S\n"
            "names = ('chdtr', 'chdtrc', 'chdtri', 'fdtrc', 'gammaln', 'ndtr', 'ndtri', "
            "'stdtrit')\n"
            "print(all(getattr(S, n) is getattr(special, n) for n in names), "
            "S._ufuncs is special._U)\n"
            "import scipy.stats\n"
            "print(scipy.stats.norm.cdf(1.0) == S.ndtr(1.0))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert out[0] == "[]"
    assert "scipy/special/_ufuncs" in out[1]
    assert out[2] == "True True"
    assert out[3] == "True"


def test_same_values_as_scipy_special():
    import scipy.special as S

    from train_estimation.core.numerics import special

    x = np.array([1e-3, 0.3, 1.0, 2.5, 40.0, 700.0])
    p = np.array([1e-12, 1e-3, 0.2, 0.5, 0.9, 1 - 1e-9])
    for k in (1.0, 3.0, 7.5):
        assert special.chdtr(k, x).tobytes() == S.chdtr(k, x).tobytes()
        assert special.chdtrc(k, x).tobytes() == S.chdtrc(k, x).tobytes()
        assert special.chdtri(k, p).tobytes() == S.chdtri(k, p).tobytes()
        assert special.fdtrc(k, 4.0, x).tobytes() == S.fdtrc(k, 4.0, x).tobytes()
        assert special.stdtrit(k, p).tobytes() == S.stdtrit(k, p).tobytes()
    assert special.gammaln(x).tobytes() == S.gammaln(x).tobytes()
    assert special.ndtr(x - 2.0).tobytes() == S.ndtr(x - 2.0).tobytes()
    assert special.ndtri(p).tobytes() == S.ndtri(p).tobytes()
    z = -np.array([0.05, 0.2, 0.3, 1 / np.e])
    assert special.lambertw(z).tobytes() == S.lambertw(z).tobytes()
    assert special.lambertw(-0.3).real == S.lambertw(-0.3).real
