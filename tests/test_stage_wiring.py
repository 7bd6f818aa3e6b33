"""The Pipeline hands its parts what they need, never a way back into itself (#53 item 2): no lambda and
no method of its own passed to a part it makes (the refiner, the heading observer, ...), and none set
on a part after it was made. A part that calls back into the Pipeline depends on the order the Pipeline
does things in, which nothing but reading both shows."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def callbacks_into(source, class_name):
    """[(line, what)] of each lambda, or method of `class_name` bound to self, that the class's methods
    pass to a call or assign to another object's attribute."""
    tree = ast.parse(source)
    cls = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == class_name)
    methods = {n.name for n in cls.body if isinstance(n, ast.FunctionDef)}

    def way_back(node):
        if isinstance(node, ast.Lambda):
            return True
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "self":
            return node.attr in methods
        if isinstance(node, (ast.Tuple, ast.List)):
            return any(way_back(e) for e in node.elts)
        return False

    found = []
    for fn in (n for n in cls.body if isinstance(n, ast.FunctionDef)):
        for node in ast.walk(fn):
            if isinstance(node, ast.Call):
                for arg in [*node.args, *(k.value for k in node.keywords)]:
                    if way_back(arg):
                        found.append((arg.lineno, f"{ast.unparse(node.func)}(... {ast.unparse(arg)} ...)"))
            elif isinstance(node, ast.Assign) and way_back(node.value):
                for target in node.targets:
                    if isinstance(target, ast.Attribute) and isinstance(target.value, ast.Attribute):
                        found.append((node.lineno, f"{ast.unparse(target)} = {ast.unparse(node.value)}"))
    return found


def test_the_pipeline_hands_its_parts_no_way_back_into_itself():
    assert callbacks_into((ROOT / "edge" / "pipeline.py").read_text(), "Pipeline") == []


def test_a_callback_handed_or_set_is_found():
    code = ("class Pipeline:\n"
            "    def __init__(self):\n"
            "        self.refiner = Refiner(self._forward_rows, compiled=(lib, lambda: self.slot))\n"
            "        self.heading.decoder_fk = self._row_fk\n"
            "        self.ok = Part(self.path.forward_rows, self.buffer)\n"
            "    def _forward_rows(self): pass\n"
            "    def _row_fk(self): pass\n")
    assert sorted(line for line, _ in callbacks_into(code, "Pipeline")) == [3, 3, 4]
