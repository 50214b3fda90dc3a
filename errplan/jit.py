"""numba behind one decorator, and the one line a first run prints when it compiles.

Every compiled kernel of errplan is declared with :func:`njit` (numba's, with ``cache=True`` by default).
Compiled code is cached on disk beside the sources (numba's ``__pycache__``, or ``$NUMBA_CACHE_DIR``), so
a machine compiles each kernel once, on the first command that needs it. When numba looks an errplan
kernel up in that cache and misses, i.e. just before it compiles, errplan prints one line on stderr
(once per process): what it compiles (the area of the kernel that missed, and its name), that no earlier
run cached it, and that each kernel is compiled once, by the first command that needs it, so a later
command that needs other kernels (``fields --rho-star`` after the demo, a tolerance query, a URDF arm of
its own) compiles those and says so too. A first run never sits silent; a warm run says nothing.
``ERRPLAN_COMPILE_NOTICE=0`` silences it.

How: numba's ``FunctionCache.load_overload`` is wrapped here; a ``None`` result for a function of errplan
is a compile about to start. The same wrapper keys each errplan kernel's cache entry on the sources of
everything it calls as well as its own (:func:`closure_digest`): numba alone checks only the kernel's own
file, and a kernel whose callee in another file changed would load stale.

Constant arguments are compile-time constants. numba compiles a kernel once per distinct argument types,
and a constant passed from compiled code (``gval(d, ...)`` with ``d`` the literal ``2``) is a type of
its own, ``Literal[int](2)``; but numba prunes a branch only on constants it can see, not on such an
argument, so ``if d == 2: planar else: spatial`` compiled both. errplan's kernels run a pass of their own
(:class:`LiteralArgsAreConstants`, through numba's ``pipeline_class`` option) that turns an integer or
boolean literal argument into a constant before numba prunes: the planar search compiles no 3-D code.
A function forced inline (``inline="always"``) is inlined before that pruning, branches and all: a
dispatch on ``d`` belongs in the caller, not in an inlined helper. The fields' entry kernels take no ``d``:
each is compiled from a copy of the function with ``d`` a constant of its globals
(:func:`errplan.fields.kernels._per_dim`).

Two measures make a first run's compile shorter, neither changing what a kernel computes: compiled
callers call wrapperless twins of their callees (:class:`Dispatcher`), and numba's typing of a built-in
or overloaded call is remembered per function and argument types (:func:`_memoize_call_types`).
Together about a quarter off the URDF arm's and the planar search's cold compile (23 -> 17 s on the
reference machine); the fields they compute are identical.

The lowest layer: numba and the standard library only.
"""
from __future__ import annotations

import hashlib
import os
import sys
import types as _pytypes
from types import ModuleType
from typing import Callable, Iterable

import numba
import numpy as np
from numba.core import caching, ir, sigutils, types
from numba.core.compiler import CompilerBase, DefaultPassBuilder
from numba.core.compiler_machinery import FunctionPass, register_pass
from numba.core.registry import CPUDispatcher
from numba.core.untyped_passes import IRProcessing

#: where the notice sends a reader for how long compiling takes (measured there, not guessed here)
COMPILE_TIMES = "docs/benchmarks.md#first-run"

#: what the kernels of a module (the longest matching prefix) are for, as the notice names them
AREAS = (
    ("errplan.fields", "the worst-case fields"),
    ("errplan.anatomy.setup", "the setup's hull distances"),
    ("errplan.anatomy", "the anatomy's clearances"),
    ("errplan.gains", "the gains and the simulation"),
    ("errplan.kinematics.urdf.reachmap", "the URDF arm's reachability map"),
    ("errplan.kinematics.urdf.broadphase", "the arms' collision checks"),
    ("errplan.kinematics.urdf", "the URDF arm's kinematics"),
    ("errplan.kinematics", "the planar arm's kinematics"),
    ("errplan.linalg", "small linear algebra"),
    ("errplan.planning", "the planner's cell walks"),
)

_STATE = {"announced": False, "label": "errplan"}


@register_pass(mutates_CFG=True, analysis_only=False)
class LiteralArgsAreConstants(FunctionPass):
    """An integer or boolean argument whose type is a literal (a constant at the call site) becomes that
    constant in the function's IR, before numba's dead-branch pruning: a branch on it is compiled only
    the way it goes."""

    _name = "errplan_literal_args_are_constants"

    def __init__(self):
        FunctionPass.__init__(self)

    def run_pass(self, state):
        changed = False
        for block in state.func_ir.blocks.values():
            for stmt in block.body:
                if isinstance(stmt, ir.Assign) and isinstance(stmt.value, ir.Arg):
                    ty = state.args[stmt.value.index]
                    if isinstance(ty, (types.IntegerLiteral, types.BooleanLiteral)):
                        stmt.value = ir.Const(ty.literal_value, stmt.value.loc)
                        changed = True
        return changed


class Compiler(CompilerBase):
    """numba's nopython pipeline with :class:`LiteralArgsAreConstants` before the branch pruning."""

    def define_pipelines(self):
        pm = DefaultPassBuilder.define_nopython_pipeline(self.state)
        pm.add_pass_after(LiteralArgsAreConstants, IRProcessing)
        pm.finalize()
        return [pm]


class Dispatcher(CPUDispatcher):
    """numba's CPU dispatcher, with two changes for calls from compiled code.

    - A constant argument (``f(x, 0)``, ``f(x, True)``) reuses the specialization for the argument's plain
      type: a constant is a new specialization (and a compile) only for the parameters named in
      :attr:`literal_args`.
    - Compiled callers call a twin of the kernel compiled without the wrapper that converts Python objects
      to native arguments and back (``no_cpython_wrapper``), cached on disk under its own name
      (``<name>__native``). numba builds that wrapper for every kernel it compiles, callees included, and
      optimizes and emits its machine code; for a kernel taking an arm's chain (a tuple of a dozen arrays)
      it is as large as a small kernel. Only a kernel Python calls needs one: a kernel called from Python
      (the commands' entries) is compiled with it, as before, and only when Python calls it. On the URDF
      arm's and the planar search's kernels: 7-8 % of a cold compile. A compiled caller of a kernel that
      Python has called already (and so compiled or loaded) calls that one instead of compiling a twin.
    """

    literal_args: frozenset = frozenset()
    #: whether this is the wrapperless twin of another kernel (its callers are compiled code only)
    is_native: bool = False

    def _native(self) -> "Dispatcher | None":
        """The wrapperless twin compiled callers call (made on first use; None for a twin itself)."""
        if self.is_native:
            return None
        twin = self.__dict__.get("_twin")
        if twin is None:
            g = copy_function(self.py_func, f"{self.py_func.__name__}__native")
            opts = dict(self.targetoptions, no_cpython_wrapper=True)
            twin = type(self)(py_func=g, locals=self.locals, targetoptions=opts,
                              pipeline_class=self._compiler.pipeline_class)
            twin.literal_args = self.literal_args
            twin.is_native = True
            if isinstance(self._cache, caching.FunctionCache):
                twin.enable_caching()
            self.__dict__["_twin"] = twin
        return twin

    def get_call_template(self, args, kws):
        keep = self.literal_args
        names = self.py_func.__code__.co_varnames[:self.py_func.__code__.co_argcount]
        args = tuple(a if i < len(names) and names[i] in keep else types.unliteral(a) for i, a in enumerate(args))
        kws = {k: (v if k in keep else types.unliteral(v)) for k, v in kws.items()}
        twin = self._native()
        if twin is not None and (tuple(args) in twin.overloads or tuple(args) not in self.overloads):
            return twin.get_call_template(args, kws)
        return super().get_call_template(args, kws)  # Python compiled or loaded it already: that one

    def get_overload(self, sig):
        """The compiled function a compiled caller links (numba's lowering of a call asks the callee's
        dispatcher): the twin's, where the caller was typed against it (:meth:`get_call_template`)."""
        twin = self.__dict__.get("_twin")
        if twin is not None and tuple(sigutils.normalize_signature(sig)[0]) in twin.overloads:
            return twin.get_overload(sig)
        return super().get_overload(sig)


def copy_function(f, name: str, **consts):
    """A copy of the plain function ``f`` named ``name`` (its own entry in numba's disk cache), reading the
    same globals, or a copy of them that holds ``consts``: module numbers that numba freezes as compile-time
    constants, pruning the branches they decide (:func:`errplan.fields.kernels._per_dim`)."""
    glb = dict(f.__globals__, **consts) if consts else f.__globals__
    g = _pytypes.FunctionType(f.__code__, glb, name, f.__defaults__, f.__closure__)
    g.__qualname__ = name
    g.__doc__ = f.__doc__
    return g


def njit(*args, literal_args: Iterable[str] = (), **options) -> Callable:
    """``numba.njit`` with ``cache=True`` unless given, errplan's :class:`Compiler` and :class:`Dispatcher`.
    Used as ``@njit``, ``@njit(...)`` or ``njit(f, ...)``. ``literal_args``: the parameters that are
    compile-time constants when a caller passes a constant (the dimension ``d`` of the field kernels).
    No C-callable wrapper is built (``no_cfunc_wrapper``, below) unless an option says otherwise."""
    cache = options.pop("cache", True)
    pipeline_class = options.pop("pipeline_class", Compiler)
    locals_ = options.pop("locals", {})
    targetoptions = dict(options, nopython=True, boundscheck=options.get("boundscheck"))
    # No C-callable wrapper: numba builds one beside every compiled specialization (besides the one Python
    # calls), for ``cfunc`` use and first-class function values, neither of which errplan makes. Skipping it
    # takes about 5 to 10 % off a cold compile (measured on the planar search and the URDF kernels).
    targetoptions.setdefault("no_cfunc_wrapper", True)
    keep = frozenset([literal_args] if isinstance(literal_args, str) else literal_args)

    def wrap(f):
        disp = Dispatcher(py_func=f, locals=locals_, targetoptions=targetoptions, pipeline_class=pipeline_class)
        disp.literal_args = keep
        if cache:
            disp.enable_caching()
        return disp

    if len(args) == 1 and callable(args[0]):
        return wrap(args[0])
    return wrap


def kernel_array(a: np.ndarray) -> np.ndarray:
    """``a`` as a writeable C array, copied only when it is not one already. numba types a read-only
    array (a broadcast view) apart from a writeable one and compiles a kernel once more for it; passing
    every kernel argument built from a caller's array through here keeps one specialization per kernel."""
    if type(a) is np.ndarray and a.flags.c_contiguous and a.flags.writeable:  # what np.require returns too
        return a
    return np.require(a, requirements=("C", "W"))


def cached(dispatcher) -> bool:
    """Whether the disk cache holds a kernel compiled from the current source (some specialization)."""
    cache = getattr(dispatcher, "_cache", None)
    cache_file = getattr(cache, "_cache_file", None)
    if cache_file is None:
        return True  # not cached on disk: nothing to compile ahead
    try:
        _stamp_closure(cache)
        return bool(cache_file._load_index())
    except Exception:  # an unreadable index is a compile too
        return False


#: top-level packages whose kernels are keyed on :func:`closure_digest` (a test adds its own)
CLOSURE_PACKAGES = {"errplan"}


def _code_names(code) -> set[str]:
    """The global names a function's code reads, nested code (comprehensions, closures) included."""
    names = set(code.co_names)
    for c in code.co_consts:
        if isinstance(c, type(code)):
            names |= _code_names(c)
    return names


def closure_digest(py_func) -> bytes:
    """sha256 over the sources of ``py_func`` and of every compiled function it calls, transitively, the
    plain constants (numbers, strings, tuples, arrays) they read from their module globals, and this
    module (the compile pipeline).

    numba keys a cached kernel on its own file only: a kernel whose callee in another file changed, or
    a constant it imported by name, was loaded stale (its old machine code), e.g. after a ``git pull``
    into an editable install that changed ``chain.py`` but not ``kernels.py``. errplan's kernels are
    keyed on this digest as well (:func:`_stamp_closure`)."""
    files = {__file__}
    consts: list[bytes] = []
    seen = set()
    stack = [py_func]
    while stack:
        f = stack.pop()
        code = getattr(f, "__code__", None)
        if code is None or code in seen:
            continue
        seen.add(code)
        files.add(code.co_filename)
        glb = getattr(f, "__globals__", {})
        for name in sorted(_code_names(code)):
            if name not in glb:
                continue
            v = glb[name]
            if isinstance(v, CPUDispatcher):
                stack.append(v.py_func)
            elif isinstance(v, np.ndarray):
                consts.append(f"{name}={v.dtype}{v.shape}".encode() + np.ascontiguousarray(v).tobytes())
            elif isinstance(v, (bool, int, float, complex, str, bytes, tuple, np.generic)):
                consts.append(f"{name}={v!r}".encode())
            elif isinstance(v, ModuleType) and v.__name__.split(".")[0] in CLOSURE_PACKAGES:
                files.add(getattr(v, "__file__", None) or "")
    h = hashlib.sha256()
    for path in sorted(p for p in files if p and os.path.isfile(p)):
        st = os.stat(path)
        h.update(caching._hash_source_file(path, st.st_mtime, st.st_size))
    for c in consts:
        h.update(c)
    return h.digest()


def _stamp_closure(cache) -> None:
    """Key an errplan kernel's disk cache on :func:`closure_digest` besides numba's own stamp (once per
    kernel and process, on its first lookup, when every module it calls into is loaded)."""
    cf = getattr(cache, "_cache_file", None)
    py_func = getattr(cache, "_py_func", None)
    if cf is None or getattr(cf, "_errplan_closure", False):
        return
    if getattr(py_func, "__module__", "").split(".")[0] in CLOSURE_PACKAGES:
        cf._source_stamp = (cf._source_stamp, closure_digest(py_func))
    cf._errplan_closure = True


def set_label(label: str) -> None:
    """How the notice names the run (the CLI sets ``errplan <command>``)."""
    _STATE["label"] = label


def area_of(module: str) -> str:
    """What the kernels of ``module`` are for (:data:`AREAS`), for the notice."""
    for prefix, what in AREAS:
        if module == prefix or module.startswith(prefix + "."):
            return what
    return "errplan's numerical code"


def notice(kernel=None) -> str:
    """The compile notice: the command, what it compiles first (the kernel that missed the cache) and why
    now. Each kernel is compiled once per machine, by the first command that needs it, not by the first
    command: a later command that needs kernels no earlier one did (``fields --rho-star``, a tolerance
    query, a URDF arm's map) compiles those then, and says so with the same truth."""
    first = ""
    if kernel is not None:
        name = getattr(kernel, "__name__", "?").removesuffix("__native")
        first = f", starting with {area_of(getattr(kernel, '__module__', ''))} ({name})"
    return (f"{_STATE['label']}: compiling numerical kernels that no earlier run has cached on this machine{first}; each kernel "
            f"is compiled once, by the first command that needs it, and loaded from the cache after that "
            f"(up to a few minutes of CPU; measured: {COMPILE_TIMES})")


def announce(stream=None, kernel=None) -> bool:
    """Print the compile notice (:func:`notice`, naming ``kernel``'s area) on ``stream`` (stderr) unless it
    was printed already or is silenced."""
    if _STATE["announced"] or os.environ.get("ERRPLAN_COMPILE_NOTICE", "1") == "0":
        return False
    _STATE["announced"] = True
    stream = stream or sys.stderr
    stream.write(notice(kernel) + "\n")
    stream.flush()
    return True


_load_overload = caching.FunctionCache.load_overload


def _runtime_ready(target_context) -> bool:
    """Make the target ready to run kernels loaded from the cache without numba's full ``refresh``.

    numba refreshes its target before every cache lookup: it imports and installs every typing and
    lowering registry it has (numpy's array functions, linalg, random, typed containers, jitclass ...),
    about 0.4 s of CPU in each process, only to rebuild machine code that is already compiled. A cached
    kernel needs the runtime (NRT: its allocations and reference counts) and the code generator, nothing
    else: the registries type and lower source, which a cache hit does not. So a lookup of an errplan
    kernel initializes the runtime only; a miss compiles, and numba's compile refreshes the context
    fully first (``numba.core.compiler.compile_extra``), as before. False where this numba has no such
    runtime (then the lookup is numba's own)."""
    try:
        from numba.core.runtime import rtsys

        rtsys.initialize(target_context)
    except Exception:  # pragma: no cover - another numba layout: its own lookup
        return False
    return True


def _load_overload_or_announce(self, sig, target_context):
    _stamp_closure(self)
    ours = getattr(getattr(self, "_py_func", None), "__module__", "").startswith("errplan")
    if ours and _runtime_ready(target_context):
        with self._guard_against_spurious_io_errors():
            res = self._load_overload(sig, target_context)
    else:
        res = _load_overload(self, sig, target_context)
    if res is None and ours:
        announce(kernel=getattr(self, "_py_func", None))
    return res


if getattr(caching.FunctionCache.load_overload, "__name__", "") != "_load_overload_or_announce":
    caching.FunctionCache.load_overload = _load_overload_or_announce


def _defer_blas_check() -> None:
    """Skip the scipy import that numba's array-math module makes when it is first imported.

    ``numba.np.arraymath`` checks at import time that scipy's BLAS is present
    (``numba.np.linalg.ensure_blas``). The check imports all of ``scipy.linalg`` (and starts its
    BLAS) when the first kernel loads: 0.3-0.4 s of every process here (a small planar ``errplan
    fields``: 1.94 -> 1.54 s, medians of six). Kernels loaded from the cache never need scipy. A compile
    that types ``np.dot`` or ``np.linalg`` calls the real check again. The BLAS routines themselves are
    bound from ``scipy.linalg.cython_blas`` on first call (numba's helper library). errplan depends on
    scipy, so the check would pass anyway.

    The module is therefore imported here with the import-time check replaced. The real check is put
    back before numba uses it again. With a numba whose module is already loaded, or that has no such
    check, this does nothing.
    """
    if "numba.np.arraymath" in sys.modules:
        return
    try:
        from numba.np import linalg as nla
    except ImportError:  # pragma: no cover - another numba layout: keep its own behaviour
        return
    real = getattr(nla, "ensure_blas", None)
    if real is None:  # pragma: no cover
        return
    nla.ensure_blas = lambda: None
    try:
        import numba.np.arraymath as am
    finally:
        nla.ensure_blas = real
    am.ensure_blas = real  # its own name for the check, bound at its import: the real one again


def _defer_blas_check_to_refresh() -> None:
    """Run :func:`_defer_blas_check` when numba first loads its registries (a compile's refresh), not at
    errplan's import: a run whose kernels all come from the cache never imports numba's array maths."""
    try:
        from numba.core.cpu import CPUContext
    except ImportError:  # pragma: no cover
        _defer_blas_check()
        return
    real = CPUContext.load_additional_registries
    if getattr(real, "_errplan_deferred", False):
        return

    def load_additional_registries(self):
        _defer_blas_check()
        return real(self)

    load_additional_registries._errplan_deferred = True
    load_additional_registries.__wrapped__ = real
    CPUContext.load_additional_registries = load_additional_registries


_defer_blas_check_to_refresh()


def _memoize_call_types() -> None:
    """Remember how numba typed a call of a built-in or overloaded function on given argument types.

    numba types every ``a + b``, ``math.sqrt(x)`` or ``np.empty(n)`` in a kernel by trying that function's
    templates in turn until one accepts the argument types. It does this again for every occurrence, in
    every kernel, although the answer depends on the function and the argument types alone. In errplan's
    kernels that search was about 15 % of a cold compile, its answers the same in 96 % of the calls. So
    a successful answer is kept, keyed on the function type, the typing context and the argument types.
    A failed one is not kept: it is searched again and reported as numba reports it. Types that cannot be
    hashed go straight to numba. A numba without this method keeps its own behaviour.
    """
    try:
        from numba.core.types import functions as fn
    except ImportError:  # pragma: no cover - another numba layout
        return
    resolve = getattr(fn.BaseFunction, "get_call_type", None)
    if resolve is None or getattr(resolve, "_errplan_memo", False):
        return
    memo: dict = {}

    def get_call_type(self, context, args, kws):
        try:
            key = (self, context, tuple(args), tuple(sorted(kws.items())) if kws else ())
            sig = memo.get(key)
        except TypeError:  # a type that cannot be hashed: numba's own search
            return resolve(self, context, args, kws)
        if sig is None:
            sig = resolve(self, context, args, kws)
            if sig is not None:
                memo[key] = sig
        return sig

    get_call_type._errplan_memo = True
    get_call_type.__wrapped__ = resolve
    get_call_type.__doc__ = resolve.__doc__
    fn.BaseFunction.get_call_type = get_call_type


_memoize_call_types()
