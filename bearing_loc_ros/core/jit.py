"""The compiler of the one-problem numerics: numba's ``njit``, cached on disk.

A function decorated with :data:`jit` is compiled to machine code on its first call and the
code is kept in numba's cache (``__pycache__`` beside the module, or numba's user cache
directory where that is not writable), so later processes load it instead of compiling.
Python's error model is kept (a float division by zero raises ZeroDivisionError), and no
fast-math: the compiled code performs the IEEE operations of the Python source in its order.
Every compiled function stays callable as Python through its ``py_func`` attribute, and with
``NUMBA_DISABLE_JIT=1`` the package runs the same source as plain Python (test/test_compiled.py
compares the two; under plain Python a :data:`jit_numpy` function's division by zero raises
instead of giving inf).
"""

from numba import njit

#: Decorator: compile lazily on first call, cache on disk, release the GIL while running.
jit = njit(cache=True, nogil=True)

#: The same with numpy's error model: a float division by zero gives ±inf or NaN, as the
#: array code a compiled function stands in for (``np.errstate(divide='ignore')``).
jit_numpy = njit(cache=True, nogil=True, error_model='numpy')
