"""The layering rules of docs/architecture.md, checked on the source (like import-linter)."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OURS = {"hal", "drivers", "appliance", "tools", "tests"}


def imports(pkg):
    for f in sorted((ROOT / pkg).rglob("*.py")):
        tree = ast.parse(f.read_text(), str(f))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    yield f, a.name.split(".")[0], a.name
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                yield f, node.module.split(".")[0], node.module


def test_hal_imports_nothing_of_ours():
    bad = [(str(f.relative_to(ROOT)), m) for f, top, m in imports("hal") if top in OURS]
    assert not bad, bad


def test_drivers_never_import_appliance():
    bad = [(str(f.relative_to(ROOT)), m) for f, top, m in imports("drivers")
           if top in {"appliance", "tools", "tests"}]
    assert not bad, bad


def test_perception_does_no_io():
    io_modules = {"socket", "subprocess", "serial", "can", "pymavlink", "urllib", "requests"}
    bad = [(str(f.relative_to(ROOT)), m) for f, top, m in imports("appliance/perception")
           if top in io_modules or m.startswith("drivers")]
    assert not bad, bad
    for f in (ROOT / "appliance" / "perception").rglob("*.py"):
        src = f.read_text()
        for call in ("open(", "imwrite(", "imread("):
            assert f" {call}" not in src and f"={call}" not in src, (f, call)


def test_perception_never_imports_the_appliance_config():
    """config imports the pipeline registry (to validate [perception.NAME] tables); the
    pipelines take their options objects and the field helper from appliance.schema, so the two
    never import each other."""
    bad = [(str(f.relative_to(ROOT)), m) for f, top, m in imports("appliance/perception")
           if m == "appliance.config" or m.startswith("appliance.config.")]
    assert not bad, bad


def test_tools_never_import_the_tests():
    bad = [(str(f.relative_to(ROOT)), m) for f, top, m in imports("tools") if top == "tests"]
    assert not bad, bad


def test_hal_depends_only_on_stdlib_and_numpy():
    import sys
    std = set(sys.stdlib_module_names)
    bad = [(str(f.relative_to(ROOT)), m) for f, top, m in imports("hal")
           if top not in std and top not in {"numpy", "__future__"}]
    assert not bad, bad
