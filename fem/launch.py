"""Taichi's kernel launch and a data-oriented object's attributes, without deriving again at every use
what the last one derived.

Taichi 1.7 spends 50 to 80 us of Python on each launch of a compiled kernel (measured on these
2-core machines; the kernel itself often runs in 5 to 50): it walks every argument to find
which compiled instance the call means, and builds twenty closures to set the arguments. A
contact step launches about 180 kernels, so that was 10 to 15 ms of the 20-box pile's step.

Here a kernel's call looks its instance up by the identity of its template arguments (checked
through weak references, so an object that died never matches one born at its address) and sets
its scalar arguments straight into the launch context. The first call of each instance, and any
call this does not cover (keyword arguments, ndarrays, vectors or structs as arguments, autodiff,
a Taichi restarted since), takes Taichi's own path, which compiles, checks and raises as before.

Taichi's @ti.data_oriented also replaces the class's attribute lookup with one that asks, of every
attribute, whether it is a kernel to bind (3,000 lookups a step of the pile). `data_oriented` answers
an object's own plain attributes, and a plain method of its own class, without asking.
"""

import weakref
from types import FunctionType, MethodType

import taichi as ti

from taichi._lib import core as _ti_core
from taichi.lang import kernel_impl, shell
from taichi.lang.matrix import Vector, VectorType
from taichi.types import primitive_types
from taichi.types.annotations import template
from taichi.lang.util import cook_dtype
from taichi.types.utils import is_signed

_VALUES = (int, float, bool, str, type(None))    # template arguments keyed by value, as Taichi does
PRUNE = 256                                      # instances a kernel keeps before it drops those of dead objects
_original = {}


def install():
    """Replace Taichi's Kernel.__call__ by `call` (once per process)."""
    if "call" not in _original:
        _original["call"] = kernel_impl.Kernel.__call__
        kernel_impl.Kernel.__call__ = call


def install_data_oriented():
    """ti.data_oriented <- `data_oriented` (once per process, before any class is declared with it)."""
    if "data_oriented" not in _original:
        _original["data_oriented"] = kernel_impl.data_oriented
        ti.data_oriented = kernel_impl.data_oriented = data_oriented


def data_oriented(cls):
    """Taichi's @ti.data_oriented, whose lookup answers at once an attribute of the object's own (not a
    function: Taichi binds a kernel kept there) and else a plain method of its class (not its subclass's),
    as Python's own lookup would (Taichi's only binds kernels)."""
    cls = _original["data_oriented"](cls)
    taichi_getattr, own = cls.__getattribute__, cls.__dict__
    methods = {name: f for name, f in own.items() if type(f) is FunctionType and not hasattr(f, "_is_wrapped_kernel")}

    def lookup(obj, item):
        if type(own.get(item)) is not property:            # a property comes before the object's own
            value = object.__getattribute__(obj, "__dict__").get(item, lookup)
            if value is not lookup:                         # the object's own (a test's stand-in for a method too)
                if type(value) is not FunctionType:
                    return value
            elif item in methods and type(obj) is cls:
                return MethodType(methods[item], obj)
        return taichi_getattr(obj, item)

    cls.__getattribute__ = lookup
    return cls


def uninstall():
    """Taichi's own launch again (a test compares the two)."""
    if "call" in _original:
        kernel_impl.Kernel.__call__ = _original.pop("call")


class Plan:
    """What one kernel's calls need: which arguments are templates, and how each scalar one is set
    (`setter`: "float", "int" or "uint"); `instances`: key -> Instance."""

    def __init__(self, kernel):
        self.templates, self.scalars, self.quick = [], [], True
        slot = 0
        for i, argument in enumerate(kernel.arguments):
            annotation = argument.annotation
            if isinstance(annotation, template):
                self.templates.append(i)
                continue
            if id(annotation) in primitive_types.real_type_ids:
                self.scalars.append((i, (slot,), "float"))
            elif id(annotation) in primitive_types.integer_type_ids:
                self.scalars.append((i, (slot,), "int" if is_signed(cook_dtype(annotation)) else "uint"))
            else:                                   # ndarrays, vectors, structs: Taichi's own path
                self.quick = False
            slot += 1
        self.count = len(kernel.arguments)
        self.returns = [_getter(kind) for kind in kernel.return_type or ()]
        self.instances, self.compiled = {}, kernel.compiled_kernels


class Instance:
    """One compiled instance: the Taichi kernel and weak references to the template arguments keyed by identity."""

    def __init__(self, compiled, held):
        self.compiled = compiled
        self.held = held


def _key(args, templates):
    return tuple(a if type(a) in _VALUES else id(a) for a in (args[i] for i in templates))


def call(kernel, *args, **kwargs):
    """Kernel.__call__: the compiled instance these arguments mean, launched."""
    plan = kernel.__dict__.get("_quick_plan")
    if plan is None or plan.compiled is not kernel.compiled_kernels:    # new, or Taichi restarted (reset)
        plan = kernel._quick_plan = Plan(kernel)
    runtime = kernel.runtime
    if (kwargs or not plan.quick or len(args) != plan.count or kernel.autodiff_mode != kernel_impl.AutodiffMode.NONE
            or runtime.fwd_mode_manager or runtime.target_tape):
        return _original["call"](kernel, *args, **kwargs)
    key = _key(args, plan.templates)
    instance = plan.instances.get(key)
    if instance is None or any(ref() is not args[i] for i, ref in instance.held):
        instance = _instance(kernel, plan, key, args)
        if instance is None:
            return _original["call"](kernel, *args)
        return kernel.launch_kernel(instance.compiled, *args)     # the first launch compiles: Taichi's own
    values = []
    for i, slot, setter in plan.scalars:
        value = args[i]
        if not isinstance(value, (int, float) if setter == "float" else int):
            return _original["call"](kernel, *args)       # Taichi's own check and message
        values.append((slot, setter, value))
    if runtime.global_vars or runtime.matrix_fields or not runtime.materialized:
        runtime.materialize()                              # fields made since the last launch
    context = instance.compiled.make_launch_context()
    for slot, setter, value in values:
        if setter == "float":
            context.set_arg_float(slot, float(value))
        elif setter == "int":
            context.set_arg_int(slot, int(value))
        else:
            context.set_arg_uint(slot, int(value))
    program = runtime.prog
    try:
        program.launch_kernel(program.compile_kernel(program.config(), program.get_device_caps(), instance.compiled),
                              context)
    except Exception as e:                                # as Taichi's own launch raises it
        raise kernel_impl.handle_exception_from_cpp(e) from None
    returns = kernel.return_type
    if returns is None and not kernel.has_print:
        return None
    program.synchronize()                                 # Taichi's sync, its fields materialised above
    if kernel.has_print and shell.pybuf_enabled:          # a notebook's stdout: what the kernel printed
        print(_ti_core.pop_python_print_buffer(), end="")
    if returns is None:
        return None
    out = []
    for i, (getter, size, dtype) in enumerate(plan.returns):
        if getter is None:                                # a matrix, a struct: Taichi's own
            out.append(kernel.construct_kernel_ret(context, returns[i], (i,)))
        elif size is None:
            out.append(getattr(context, getter)((i,)))
        else:
            out.append(Vector([getattr(context, getter)((i, j)) for j in range(size)], dt=dtype))
    return out[0] if len(out) == 1 else out


def _getter(kind):
    """(the launch context's getter, the vector's size or None for a scalar, its dtype) of a return type;
    getter None where this does not cover the type."""
    dtype, size = kind, None
    if isinstance(kind, VectorType):
        dtype, size = kind.dtype, kind.n
    elif not id(kind) in primitive_types.type_ids:
        return None, None, None
    if dtype in primitive_types.real_types:
        return "get_struct_ret_float", size, dtype
    if dtype in primitive_types.integer_types:
        return ("get_struct_ret_int" if is_signed(cook_dtype(dtype)) else "get_struct_ret_uint"), size, dtype
    return None, None, None


def _instance(kernel, plan, key, args):
    """The instance these arguments mean, compiled (Taichi's own lookup: it announces and compiles a new one),
    and kept under `key`; None where a template argument keyed by identity takes no weak reference."""
    try:
        held = [(i, weakref.ref(args[i])) for i in plan.templates if type(args[i]) not in _VALUES]
    except TypeError:
        return None
    compiled = kernel.compiled_kernels[kernel.ensure_compiled(*args)]
    if len(plan.instances) >= PRUNE:                       # objects made anew for each call: forget the dead
        plan.instances = {k: kept for k, kept in plan.instances.items() if all(ref() is not None for _, ref in kept.held)}
    instance = plan.instances[key] = Instance(compiled, held)
    return instance
