"""Graph passes applied to exported ONNX models (onnx only, no torch).

:func:`int32_indices`: torch's ``gather`` requires int64 indices, so the traced graph
computes every per-pixel index (the map-table index, the 2x2 bilinear neighbours shared by
the colour channels) in int64. ONNX ``GatherElements`` accepts int32 indices; computing the
index chains in int32 halves the memory traffic of their integer nodes and of the gathers'
index reads (the saving is measured in docs/runtime.md). Values are unchanged as long as
they fit in int32, which is checked for every constant in the chain (canvas-sized indices
are far below 2^31).
"""

from __future__ import annotations

import numpy as np

_ARITH = ("Add", "Mul", "Sub")
_SHAPE = ("Flatten", "Reshape", "Unsqueeze", "Squeeze")


def _index_chain(node, producers, inits, outputs):
    """Nodes and initializers computing ``node``'s index input, or None when the chain
    contains anything but Cast / integer arithmetic / reshapes / constants."""
    chain, chain_inits, seen = [], set(), set()
    stack = [node.input[1]]
    while stack:
        t = stack.pop()
        if t in seen:
            continue
        seen.add(t)
        if t in inits:
            chain_inits.add(t)
            continue
        p = producers.get(t)
        if p is None or t in outputs:
            return None
        if p.op_type in ("Cast", "ConstantOfShape", "Constant"):
            chain.append(p)
        elif p.op_type in _ARITH:
            chain.append(p)
            stack += list(p.input)
        elif p.op_type in _SHAPE:
            chain.append(p)
            stack.append(p.input[0])
        else:
            return None
    return chain, chain_inits


def int32_indices(model) -> int:
    """Rewrite the int64 index chains of ``GatherElements`` nodes to int32 (in place).

    Chains that share tensors (one index read by several gathers, e.g. one per colour
    channel) are rewritten together. A group of chains is rewritten only when each of its
    tensors is used by the group alone (its chain nodes, or its gathers as their index)
    and every constant fits in int32. Returns the number of gathers rewritten.
    """
    from onnx import TensorProto, numpy_helper

    g = model.graph
    producers = {o: n for n in g.node for o in n.output}
    consumers: dict[str, list] = {}
    for n in g.node:
        for i in n.input:
            consumers.setdefault(i, []).append(n)
    inits = {t.name: t for t in g.initializer}
    outputs = {o.name for o in g.output}
    chains = {}
    for node in g.node:
        if node.op_type == "GatherElements":
            found = _index_chain(node, producers, inits, outputs)
            if found is not None:
                chains[id(node)] = (node, *found)
    # group gathers whose chains share a tensor (union-find over tensor names)
    parent = {k: k for k in chains}

    def root(k):
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    owner: dict[str, int] = {}
    for k, (_, chain, chain_inits) in chains.items():
        for t in [o for p in chain for o in p.output] + sorted(chain_inits):
            if t in owner:
                parent[root(k)] = root(owner[t])
            else:
                owner[t] = k
    groups: dict[int, list] = {}
    for k in chains:
        groups.setdefault(root(k), []).append(chains[k])
    done = 0
    for members_ in groups.values():
        gathers = [m[0] for m in members_]
        chain = list({id(p): p for m in members_ for p in m[1]}.values())
        chain_inits = set().union(*(m[2] for m in members_))
        arrays = {t: numpy_helper.to_array(inits[t]) for t in chain_inits}
        if any(a.dtype != np.int64 or (a.size and np.abs(a).max() >= 2 ** 31) for a in arrays.values()):
            continue
        members = {id(p) for p in chain}
        gather_ids = {id(n) for n in gathers}
        tensors = {o for p in chain for o in p.output} | chain_inits
        # shape inputs of Reshape are int64 by definition: they must not be in the chain
        if any(p.op_type == "Reshape" and p.input[1] in tensors for p in chain):
            continue
        if any(id(c) not in members and not (id(c) in gather_ids and c.input[1] == t and c.input[0] != t)
               for t in tensors for c in consumers.get(t, [])):
            continue
        if any(p.op_type == "Cast" and next(a.i for a in p.attribute if a.name == "to") != TensorProto.INT64
               for p in chain):
            continue
        for p in chain:
            for a in p.attribute:
                if p.op_type == "Cast" and a.name == "to":
                    a.i = TensorProto.INT32
                elif p.op_type in ("ConstantOfShape", "Constant") and a.name == "value":
                    a.t.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(a.t).astype(np.int32), a.t.name))
        for t, a in arrays.items():
            inits[t].CopyFrom(numpy_helper.from_array(a.astype(np.int32), t))
        stale = [v for v in g.value_info if v.name in tensors]
        for v in stale:
            g.value_info.remove(v)
        done += len(gathers)
    return done
