"""The two kernels written in LLVM IR: a sparse row times a block of four right-hand sides (row_dot4) and its scatter
(row_axpy4), for the implicit integrator's triangular solves (implicit._forward, implicit._backward; docs/solver.md
"Implicit integrator").

Written in numba, the row's sum over its entries, s_c -= L_pq z[q, c] for the three coordinates, compiles to three
scalar loads and multiply-adds per entry: LLVM does not vectorise a reduction over the three right-hand sides, and
the solves are then bound by the core's load ports. Here z has a fourth, unused column and each entry is one
4-wide load of z[j, 0:4] and one 4-wide fused multiply-add, summed in four accumulators (the rows are short, ~9
entries, and a single accumulator would wait on the multiply-add's latency). Measured on the bundled limb's factor
(Intel Xeon, rocketlake): the forward and backward passes 51 us against 80 us.

row_dot4 is the plain loop `sum over q in [q0, q1) of Lx[q] * z[Lj[q], :]` (tests/test_solver_implicit.py checks
it against that), with the sum's order changed: results differ from it in the last bits. row_axpy4 is the plain loop
`z[Lj[q], :3] -= Lx[q] * w` (checked the same way): the backward pass reads the factor's rows as the forward pass
does, so the factor is stored once (docs/solver.md, "The working set")."""
from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

_K = 4          # accumulators (entries in flight per iteration; a power of 2)


def _row_types(Lx, Lj, z, q0, q1) -> bool:
    """Whether the arguments are a factor's row as the two kernels read it: Lx float64 (N,), Lj uint32 (N,), z
    float64 (n, 4) C-contiguous, q0 and q1 integers."""
    return (isinstance(Lx, types.Array) and Lx.dtype == types.float64 and Lx.ndim == 1
            and isinstance(Lj, types.Array) and Lj.dtype == types.uint32 and Lj.ndim == 1
            and isinstance(z, types.Array) and z.dtype == types.float64 and z.ndim == 2 and z.layout == 'C'
            and isinstance(q0, types.Integer) and isinstance(q1, types.Integer))


def _row_values(context, builder, sig, args):
    """(the data pointers of Lx, Lj and z, q0 and q1 as i64) of a row kernel's first five arguments."""
    lx, lj, zz, a, b = args[:5]
    data = [context.make_array(sig.args[k])(context, builder, v).data for k, v in enumerate((lx, lj, zz))]
    i64 = ir.IntType(64)
    a, b = (v if v.type.width == 64 else (builder.sext if t.signed else builder.zext)(v, i64)
            for v, t in ((a, sig.args[3]), (b, sig.args[4])))
    return (*data, a, b)


@intrinsic
def row_dot4(typingctx, Lx, Lj, z, q0, q1):
    """(s0, s1, s2, s3) = sum over q in [q0, q1) of Lx[q] * z[Lj[q], 0:4]. Lx float64 (N,), Lj uint32 (N,) (unsigned:
    read as an offset), z float64 (n, 4) C-contiguous (its rows read as one 4-wide load each), q0 <= q1 integers."""
    if not _row_types(Lx, Lj, z, q0, q1):
        return None
    sig = types.UniTuple(types.float64, 4)(Lx, Lj, z, q0, q1)

    def codegen(context, builder, sig, args):
        x_data, j_data, z_data, a, b = _row_values(context, builder, sig, args)
        i32, i64 = ir.IntType(32), ir.IntType(64)
        v4 = ir.VectorType(ir.DoubleType(), 4)
        fma = cgutils.get_or_insert_function(builder.module, ir.FunctionType(v4, [v4, v4, v4]), 'llvm.fma.v4f64')
        zero, undef = ir.Constant(v4, [0.0] * 4), ir.Constant(v4, ir.Undefined)
        splat = ir.Constant(ir.VectorType(i32, 4), [0, 0, 0, 0])

        def term(q, acc):                       # acc + Lx[q] * z[Lj[q], 0:4]
            j = builder.zext(builder.load(builder.gep(j_data, [q])), i64)
            lv = builder.insert_element(undef, builder.load(builder.gep(x_data, [q])), ir.Constant(i32, 0))
            row = builder.bitcast(builder.gep(z_data, [builder.mul(j, ir.Constant(i64, 4))]), v4.as_pointer())
            return builder.call(fma, [builder.shuffle_vector(lv, undef, splat), builder.load(row, align=8), acc])

        fn, entry = builder.function, builder.block
        loop, body, tail_start, tail, tail_body, done = (fn.append_basic_block(f'row_dot4.{n}') for n in
                                                          ('loop', 'body', 'tail_start', 'tail', 'tail_body', 'done'))
        builder.branch(loop)
        builder.position_at_end(loop)           # _K entries per iteration, one accumulator each
        q = builder.phi(i64)
        accs = [builder.phi(v4) for _ in range(_K)]
        q.add_incoming(a, entry)
        for acc in accs:
            acc.add_incoming(zero, entry)
        builder.cbranch(builder.icmp_signed('<', builder.add(q, ir.Constant(i64, _K - 1)), b), body, tail_start)
        builder.position_at_end(body)
        nxt = [term(builder.add(q, ir.Constant(i64, k)), accs[k]) for k in range(_K)]
        q.add_incoming(builder.add(q, ir.Constant(i64, _K)), body)
        for acc, n in zip(accs, nxt):
            acc.add_incoming(n, body)
        builder.branch(loop)
        builder.position_at_end(tail_start)     # the accumulators summed, then the last < _K entries one by one
        while len(accs) > 1:
            accs = [builder.fadd(accs[k], accs[k + 1]) for k in range(0, len(accs), 2)]
        total = accs[0]
        builder.branch(tail)
        builder.position_at_end(tail)
        tq, ts = builder.phi(i64), builder.phi(v4)
        tq.add_incoming(q, tail_start)
        ts.add_incoming(total, tail_start)
        builder.cbranch(builder.icmp_signed('<', tq, b), tail_body, done)
        builder.position_at_end(tail_body)
        tq.add_incoming(builder.add(tq, ir.Constant(i64, 1)), tail_body)
        ts.add_incoming(term(tq, ts), tail_body)
        builder.branch(tail)
        builder.position_at_end(done)
        return context.make_tuple(builder, sig.return_type,
                                  [builder.extract_element(ts, ir.Constant(i32, k)) for k in range(4)])

    return sig, codegen


@intrinsic
def row_axpy4(typingctx, Lx, Lj, z, q0, q1, w0, w1, w2):
    """z[Lj[q], 0:4] -= Lx[q] * (w0, w1, w2, 0) for q in [q0, q1): the scatter of one row of a triangular factor
    (implicit._backward_rows), each entry one 4-wide load, fused multiply-add and store of z's row. The entries of a
    row name distinct rows of z, so the order of the entries does not change the result. Types as row_dot4's; w0, w1,
    w2 float64."""
    if not (_row_types(Lx, Lj, z, q0, q1) and all(isinstance(w, types.Float) for w in (w0, w1, w2))):
        return None
    sig = types.none(Lx, Lj, z, q0, q1, w0, w1, w2)

    def codegen(context, builder, sig, args):
        x_data, j_data, z_data, a, b = _row_values(context, builder, sig, args)
        i32, i64 = ir.IntType(32), ir.IntType(64)
        v4 = ir.VectorType(ir.DoubleType(), 4)
        ws = [context.cast(builder, w, t, types.float64) for w, t in zip(args[5:], sig.args[5:])]
        fma = cgutils.get_or_insert_function(builder.module, ir.FunctionType(v4, [v4, v4, v4]), 'llvm.fma.v4f64')
        undef = ir.Constant(v4, ir.Undefined)
        wv = ir.Constant(v4, [0.0] * 4)
        for k, w in enumerate(ws):
            wv = builder.insert_element(wv, builder.fsub(ir.Constant(ir.DoubleType(), 0.0), w), ir.Constant(i32, k))
        splat = ir.Constant(ir.VectorType(i32, 4), [0, 0, 0, 0])
        fn, entry = builder.function, builder.block
        loop, body, done = (fn.append_basic_block(f'row_axpy4.{n}') for n in ('loop', 'body', 'done'))
        builder.branch(loop)
        builder.position_at_end(loop)
        q = builder.phi(i64)
        q.add_incoming(a, entry)
        builder.cbranch(builder.icmp_signed('<', q, b), body, done)
        builder.position_at_end(body)
        j = builder.zext(builder.load(builder.gep(j_data, [q])), i64)
        lv = builder.insert_element(undef, builder.load(builder.gep(x_data, [q])), ir.Constant(i32, 0))
        row = builder.bitcast(builder.gep(z_data, [builder.mul(j, ir.Constant(i64, 4))]), v4.as_pointer())
        builder.store(builder.call(fma, [builder.shuffle_vector(lv, undef, splat), wv, builder.load(row, align=8)]),
                      row, align=8)
        q.add_incoming(builder.add(q, ir.Constant(i64, 1)), body)
        builder.branch(loop)
        builder.position_at_end(done)
        return context.get_dummy_value()

    return sig, codegen
