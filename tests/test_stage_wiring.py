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
    methods = {n.name for n in cls.body if isinstance(n, ast.FunctionDef)      # a property is a value
               and not any(ast.unparse(d) == "property" for d in n.decorator_list)}

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


# What the Pipeline may read of a frame path: the stages (edge.frame.FramePath) and the four things
# docs/architecture.md names beside them.
FRAME_PATH_INTERFACE = {"inputs", "poses", "judge", "switch_to", "emit", "ring_changed", "forward_rows",
                        "set_target_row", "smooth_recomputed", "row_pose", "bind_decoder", "reset",
                        "core", "fused_criteria", "ae_ready"}


def pipeline_reads(source, holders=("self",), names=("p", "pipe")):
    """[(line, expression)] of each attribute read through a pipeline handle: a name in `names`, or
    self.p / self.pipe / self.pipeline."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Attribute):
            continue
        v = node.value
        if (isinstance(v, ast.Name) and v.id in names) or (
                isinstance(v, ast.Attribute) and isinstance(v.value, ast.Name) and v.value.id in holders
                and v.attr in ("p", "pipe", "pipeline")):
            found.append((node.lineno, ast.unparse(node)))
    return found


def test_the_frame_paths_read_nothing_of_the_pipeline():
    for name in ("frame_numpy.py", "frame_compiled.py"):
        assert pipeline_reads((ROOT / "edge" / name).read_text()) == [], name
    tree = ast.parse((ROOT / "edge" / "pipeline.py").read_text())
    made = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and ast.unparse(n.func) in ("NumpyFrame", "CompiledFrame")]
    assert len(made) == 2 and not any(isinstance(a, ast.Name) and a.id == "self" for n in made for a in n.args)


def test_the_pipeline_reads_only_the_frame_paths_interface():
    tree = ast.parse((ROOT / "edge" / "pipeline.py").read_text())
    read = {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Attribute)
            and isinstance(n.value.value, ast.Name) and n.value.value.id == "self" and n.value.attr in ("path", "reference")}
    assert read and read <= FRAME_PATH_INTERFACE, read - FRAME_PATH_INTERFACE


def test_a_read_through_the_pipeline_is_found():
    code = "class F:\n    def f(self):\n        p = self.p\n        return p.buffer, self.p.decoder, self.spec.fps\n"
    assert sorted(expr for _, expr in pipeline_reads(code)) == ["p.buffer", "self.p.decoder"]
