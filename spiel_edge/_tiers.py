"""Two forms of the same kernels in one process: compiled and interpreted.

Every kernel made by ``spiel_edge._jit.jit`` is a numba dispatcher that keeps the Python
function it compiles (``py_func``). :class:`Interpreted` builds, for each, a twin: that
function with its globals (and closure cells) rebound to the other twins, so an interpreted
kernel calling another kernel calls its interpreted form (numba decides interpreted or
compiled when a function is decorated: the two forms cannot share module globals, or one
tier's kernels calling the other's would compile in place). :meth:`Interpreted.enter` puts
the twins where the Python code around the kernels finds them (every module global of
``spiel_edge.*`` and ``spiel_edge.protocol.*`` bound to a kernel, and the stream decoder's
pure-Python path), :meth:`Interpreted.leave` puts the dispatchers back: the objects that hold
state (pipelines, trackers, sessions, sinks) are the same on both tiers.

While the twins run, the calls from Python into them are noted with the argument types numba
would compile them for (:attr:`Interpreted.calls`): that is the compile plan of what the
command really uses (``spiel_edge.runtime.tiered``).
"""

from __future__ import annotations

import inspect
import logging
import sys
import types
from collections.abc import Callable

log = logging.getLogger(__name__)

KERNELS: list = []  # every dispatcher spiel_edge._jit.jit made, in the order they were made
# kernel id -> (kernel, a numpy function giving its py_func's results bit for bit, faster
# interpreted): the twin of the hottest interpreted kernels (issue 39: the interpreted tier
# keeps up with the board)
NUMPY_FORMS: dict[int, tuple[object, Callable]] = {}
OWN_PREFIXES = ("spiel_edge.",)


def register(dispatcher) -> None:
    KERNELS.append(dispatcher)


def numpy_form(dispatcher) -> Callable[[Callable], Callable]:
    """Decorator: ``fn`` is ``dispatcher``'s interpreted form (the same arguments and results,
    bit for bit as its Python function: checked in tests; it calls no kernel)."""

    def wrap(fn: Callable) -> Callable:
        NUMPY_FORMS[id(dispatcher)] = (dispatcher, fn)
        return fn

    return wrap


def is_inlined(dispatcher) -> bool:
    """An ``inline="always"`` helper: compiled into its callers, never alone."""
    return dispatcher.targetoptions.get("inline", "never") != "never"


def qualified_name(dispatcher) -> str:
    f = dispatcher.py_func
    return f"{f.__module__}.{f.__name__}"


def where(dispatcher) -> tuple[str, str]:
    """(module, attribute) naming ``dispatcher`` in its own module (the compile plan's key)."""
    f = dispatcher.py_func
    module = sys.modules.get(f.__module__)
    if module is not None and getattr(module, f.__name__, None) is dispatcher:
        return f.__module__, f.__name__
    for name, value in vars(module or {}).items():
        if value is dispatcher:
            return f.__module__, name
    return f.__module__, f.__name__


def _own_modules():
    return [
        m
        for name, m in list(sys.modules.items())
        if m is not None and name.startswith(OWN_PREFIXES) and hasattr(m, "__dict__")
    ]


def callees(dispatcher, by_id: dict[int, object]) -> set[int]:
    """The kernels ``dispatcher``'s code names (numba types every branch: each one compiles
    with it), as ids; from the globals its code and nested code objects read."""
    found: set[int] = set()
    glb = dispatcher.py_func.__globals__
    stack = [dispatcher.py_func.__code__]
    while stack:
        code = stack.pop()
        for name in code.co_names:
            value = getattr(glb.get(name), "dispatcher", glb.get(name))  # an interpreted wrapper
            if value is not None and id(value) in by_id:
                found.add(id(value))
        stack.extend(c for c in code.co_consts if isinstance(c, types.CodeType))
    for cell in dispatcher.py_func.__closure__ or ():
        try:
            value = cell.cell_contents
        except ValueError:
            continue
        if id(value) in by_id:
            found.add(id(value))
    return found


def reach(roots, kernels=None) -> list:
    """Every kernel compiled when ``roots`` compile (themselves and what they call, inlined
    helpers left out: they compile into their callers)."""
    by_id = {id(k): k for k in (kernels if kernels is not None else KERNELS)}
    seen: dict[int, object] = {}
    stack = [k for k in roots if id(k) in by_id]
    while stack:
        k = stack.pop()
        if id(k) in seen:
            continue
        seen[id(k)] = k
        stack.extend(by_id[i] for i in callees(k, by_id) if i not in seen)
    return [k for k in seen.values() if not is_inlined(k)]


class _Recorder:
    """Notes each distinct (kernel, argument types) called from Python."""

    def __init__(self) -> None:
        self.calls: dict[tuple[int, tuple], object] = {}  # (id, types) -> dispatcher
        self.failed = 0

    def note(self, dispatcher, pysig: inspect.Signature, args, kwargs) -> None:
        from numba.core import types as nbtypes

        try:
            bound = pysig.bind(*args, **kwargs)
            argtypes = []
            for name, param in pysig.parameters.items():
                if name in bound.arguments:
                    argtypes.append(dispatcher.typeof_pyval(bound.arguments[name]))
                else:
                    argtypes.append(nbtypes.Omitted(param.default))
            key = (id(dispatcher), tuple(argtypes))
        except Exception as exc:  # a value numba cannot type: the call itself will say
            self.failed += 1
            log.debug("argument types of %s not noted: %s", qualified_name(dispatcher), exc)
            return
        if key not in self.calls:
            self.calls[key] = dispatcher


class Interpreted:
    """The interpreted tier of every registered kernel."""

    def __init__(self, kernels=None) -> None:
        self.kernels = list(kernels if kernels is not None else KERNELS)
        self.twins: dict[int, Callable] = {}
        self._build()
        self.recorder = _Recorder()
        self.outer = {id(k): self._outer(k) for k in self.kernels}
        self._swapped: list[tuple[dict, str, object]] = []
        self.active = False
        # on_call() before each call from Python, for a command whose loop has no between():
        # True when the compiled tier is in place (then the call goes to the dispatcher)
        self.on_call: Callable[[], bool] | None = None

    def _build(self) -> None:
        namespaces: dict[str, dict] = {}
        for k in self.kernels:
            f = k.py_func
            ns = namespaces.setdefault(f.__module__, {})
            twin = types.FunctionType(f.__code__, ns, f.__name__, f.__defaults__, f.__closure__)
            twin.__kwdefaults__ = f.__kwdefaults__
            twin.__qualname__ = f.__qualname__
            twin.__doc__ = f.__doc__
            self.twins[id(k)] = twin
        for k in self.kernels:  # a numpy form where there is one (no kernel inside)
            if id(k) in NUMPY_FORMS:
                self.twins[id(k)] = NUMPY_FORMS[id(k)][1]
        for k in self.kernels:  # closures holding kernels: cells of the twins instead
            twin = self.twins[id(k)]
            if id(k) in NUMPY_FORMS:
                continue
            if twin.__closure__ and any(self._maps(c) for c in twin.__closure__):
                cells = tuple(types.CellType(self._mapped(c)) for c in twin.__closure__)
                self.twins[id(k)] = fixed = types.FunctionType(
                    twin.__code__, twin.__globals__, twin.__name__, twin.__defaults__, cells
                )
                fixed.__kwdefaults__, fixed.__qualname__ = twin.__kwdefaults__, twin.__qualname__
        for module_name, ns in namespaces.items():
            source = vars(sys.modules[module_name])
            ns.update({name: self.twins.get(id(v), v) for name, v in source.items()})

    def _maps(self, cell) -> bool:
        try:
            return id(cell.cell_contents) in self.twins
        except ValueError:
            return False

    def _mapped(self, cell):
        value = cell.cell_contents
        return self.twins.get(id(value), value)

    def _outer(self, dispatcher) -> Callable:
        twin = self.twins[id(dispatcher)]
        pysig = inspect.signature(dispatcher.py_func)
        recorder_of = self  # the recorder may be replaced (a new plan)

        def outer(*args, **kwargs):
            hook = recorder_of.on_call
            if hook is not None and hook():
                return dispatcher(*args, **kwargs)  # switched to the compiled tier
            recorder_of.recorder.note(dispatcher, pysig, args, kwargs)
            return twin(*args, **kwargs)

        outer.__name__ = twin.__name__
        outer.__qualname__ = twin.__qualname__
        outer.__wrapped__ = twin
        outer.dispatcher = dispatcher
        return outer

    @property
    def calls(self) -> list[tuple[object, tuple]]:
        """(dispatcher, argument types) of each distinct call from Python noted so far."""
        noted = dict(self.recorder.calls)  # one copy (atomic): the loader thread reads it
        return [(k, key[1]) for key, k in noted.items()]

    def enter(self, pure_cobs: bool = True) -> None:
        """The twins in place of the dispatchers, wherever Python code finds a kernel
        (``pure_cobs``: and the stream decoder on its pure-Python path)."""
        if self.active:
            return
        swapped = []
        modules = {id(m): m for m in _own_modules()}
        for k in self.kernels:  # and the kernels' own modules (a plugin's, a test's)
            module = sys.modules.get(k.py_func.__module__)
            if module is not None:
                modules[id(module)] = module
        for module in modules.values():
            d = vars(module)
            for name, value in list(d.items()):
                wrapper = self.outer.get(id(value))
                if wrapper is not None and value is not wrapper:
                    swapped.append((d, name, value))
                    d[name] = wrapper
        self._swapped = swapped
        self.active = True
        if pure_cobs:
            self.use_pure_cobs()

    def use_pure_cobs(self) -> None:
        """The stream decoder on its pure-Python path (the same bytes, faster than twins)."""
        cobs = sys.modules.get("spiel_edge.protocol.cobs")  # imported with the kernels
        if cobs is not None and cobs.kernels() is not None:
            self._swapped.append((vars(cobs), "_kernels", cobs._kernels))
            cobs._kernels = None

    def leave(self) -> None:
        """The dispatchers back where they were."""
        for d, name, value in reversed(self._swapped):
            d[name] = value
        self._swapped = []
        self.active = False
