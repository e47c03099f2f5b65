"""JSON values and path edits for the fuzz tests."""

from __future__ import annotations

import copy

from hypothesis import strategies as st

JSON_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**12), 10**12)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12)
    | st.sampled_from(
        [
            "",
            "..",
            "/etc/passwd",
            "images/000000.png",
            "0",
            "cam0",
            "object",
            "float16",
            "complex64",
            "int8",
            "<U3",
            "bool",
            "list",
            "base64",
        ]
    ),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=12,
)


DELETE = object()


def _paths(node, prefix=()):
    """Every (path) into a JSON-like tree, containers included."""
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node[:3]):
            yield from _paths(v, prefix + (i,))


def _set(tree, path, value):
    tree = copy.deepcopy(tree)
    if not path:
        return value
    node = tree
    for p in path[:-1]:
        node = node[p]
    if value is DELETE:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return tree
