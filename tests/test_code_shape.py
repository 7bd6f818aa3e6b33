"""The board's code stays readable top to bottom (#53): no function in edge/ or firmware_bridge/ longer
than 60 lines, and `edge run`'s Service, which composes the parts and runs the tick, under 150."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_FUNCTION_LINES, MAX_SERVICE_LINES = 60, 150


def long_functions(source, limit=MAX_FUNCTION_LINES, filename="<source>"):
    """[(name, lines)] of the functions and methods in `source` longer than `limit` lines."""
    return [(n.name, n.end_lineno - n.lineno + 1) for n in ast.walk(ast.parse(source, filename))
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.end_lineno - n.lineno + 1 > limit]


def test_no_function_of_the_board_is_over_60_lines():
    files = sorted(p for pkg in ("edge", "firmware_bridge") for p in (ROOT / pkg).rglob("*.py"))
    found = [f"{p.relative_to(ROOT)}: {name} {lines} lines" for p in files
             for name, lines in long_functions(p.read_text(), filename=str(p))]
    assert found == []


def test_the_service_is_under_150_lines():
    tree = ast.parse((ROOT / "firmware_bridge" / "service.py").read_text())
    service = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Service")
    assert service.end_lineno - service.lineno + 1 < MAX_SERVICE_LINES


def test_a_long_function_is_found():
    lines = [f"    x{i} = {i}\n" for i in range(60)]
    short, long = "".join(lines[:59]), "".join(lines)         # 60 and 61 lines with the def
    assert long_functions(f"def short():\n{short}\n\ndef long():\n{long}") == [("long", 61)]
