"""No object in the board's code reads another object's private attributes (#53): what one part needs
from another it gets through a public method, so the other can change its insides safely.

Read from the syntax tree of edge/ and firmware_bridge/: an attribute whose name starts with one
underscore, read on anything but `self` or `cls`. ctypes' `_fields_` is that library's public protocol."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PUBLIC_BY_CONVENTION = {"_fields_"}         # ctypes.Structure's field list


def private_reads(source, filename="<source>"):
    """[(line, expression)] of each `x._name` in the source where x is not self or cls."""
    found = []
    for node in ast.walk(ast.parse(source, filename)):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                and node.attr not in PUBLIC_BY_CONVENTION
                and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))):
            found.append((node.lineno, ast.unparse(node)))
    return found


def test_the_board_code_reads_no_private_attribute_of_another_object():
    files = sorted(p for pkg in ("edge", "firmware_bridge") for p in (ROOT / pkg).rglob("*.py"))
    assert len(files) > 50
    reads = [f"{p.relative_to(ROOT)}:{line}: {expr}" for p in files for line, expr in private_reads(p.read_text(), str(p))]
    assert reads == []


def test_a_private_read_through_another_name_is_caught():
    code = ("class A:\n    def f(self, other):\n        self._mine = 1\n        return other.scorer._err\n"
            "    def g(self):\n        return self.part._buf, type(self).__name__, Spec._fields_\n")
    assert private_reads(code) == [(4, "other.scorer._err"), (6, "self.part._buf")]
