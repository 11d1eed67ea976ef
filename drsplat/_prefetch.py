"""A cache prefetch hint for numba kernels that read rows by ids they learn late (`llvm.prefetch`).

The hint changes no value a kernel computes. It pays where a loop reads the row of an id it has
just loaded, e.g. the Gaussians of a tile list: the row is a cache miss the loop then waits for.
Asking for the rows of the ids a few iterations ahead overlaps those misses with the work of the
current one (flowers, the registration compositor: 12 % of its time was the wait for each tile
entry's first row; docs/raster.md). The address is only computed, never read, so an id out of
the array's range is harmless to the hardware, but callers keep to valid ids all the same.
"""

from __future__ import annotations

from llvmlite import binding, ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

_READ, _KEEP_IN_ALL_LEVELS, _DATA = 0, 3, 1  # llvm.prefetch's rw, locality and cache-type operands
# the intrinsic is mangled by its pointer type: typed (LLVM 14, numba 0.59's llvmlite) or opaque (LLVM 15 on)
_PREFETCH = "llvm.prefetch.p0i8" if binding.llvm_version_info[0] < 15 else "llvm.prefetch.p0"


@intrinsic
def prefetch_row(typingctx, array, row):
    """Hint that array[row, 0, ...] (the first byte of row `row`) will be read soon.

    array: any numba array (C, F or strided); row: an integer (no wraparound, no bounds check).
    """
    if not isinstance(array, types.Array) or not isinstance(row, types.Integer):
        return None
    signature = types.void(array, row)

    def codegen(context, builder, sig, args):
        array_type = sig.args[0]
        view = context.make_array(array_type)(context, builder, args[0])
        index = context.cast(builder, args[1], sig.args[1], types.intp)
        zero = context.get_constant(types.intp, 0)
        pointer = cgutils.get_item_pointer2(
            context, builder, view.data, cgutils.unpack_tuple(builder, view.shape), cgutils.unpack_tuple(builder, view.strides),
            array_type.layout, [index] + [zero] * (array_type.ndim - 1), wraparound=False, boundscheck=False,
        )
        byte_pointer = ir.IntType(8).as_pointer()
        int32 = ir.IntType(32)
        hint = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [byte_pointer, int32, int32, int32]), _PREFETCH)
        builder.call(hint, [builder.bitcast(pointer, byte_pointer), int32(_READ), int32(_KEEP_IN_ALL_LEVELS), int32(_DATA)])
        return context.get_dummy_value()

    return signature, codegen
