"""Settings are typed once where a command or a job reads its config and passed down as instances: below the
commands no code reads a setting by its key (``cfg["train"]["lr"]``, ``launch.get("rehearsal")``), except where a
config is typed or hashed. A static check of the package's source."""

import ast
from collections import Counter
from pathlib import Path

import nsl_hpc

PACKAGE = Path(nsl_hpc.__file__).parent
COMMANDS = {"launch", "status", "resubmit", "report", "fit", "predict", "merge", "clean", "train", "place_data", "cli",
            "__init__", "__main__"}  # nsl_hpc/<command>.py: where a command reads its config
# names that hold a config or a group of one in the package's code
SETTINGS = {"cfg", "config", "base", "launch", "values", "settings", "system_cfg", "arch_cfg", "train", "source",
            "spec", "rehearse", "launch_config", "nsl", "sweep", "launcher", "cost", "packing", "lockstep", "budget",
            "watchdog", "checkpoint", "tiers", "metric", "system", "arch", "options", "figures", "mlflow",
            "joint"}
# where a plain config is typed (config/: the owners themselves), composed per pair (pair_configs: which pairs
# have a key), upgraded from an older format before it is typed (sweep/formats.py), or hashed for task ids
BOUNDARIES = {"config", "studies/__init__.py:study_of", "studies/base.py:shared_identity",
              "studies/base.py:with_stored_defaults", "sweep/formats.py",
              "sweep/manifest.py:read_pair", "sweep/prepare.py:require_costs", "sweep/prepare.py:pair_configs",
              "sweep/launch_settings.py:launch_settings", "sweep/launch_settings.py:check_run_settings"}


def holder(node: ast.AST) -> str | None:
    """The name a subscript or ``.get`` reads from: ``cfg`` of ``cfg["x"]``, ``train`` of ``base.train["lr"]``."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return holder(node.value) if isinstance(node, ast.Subscript) else None


def read_key(node: ast.AST) -> str | None:
    """The string key a settings name is read by at ``node`` (``x["key"]``, ``x.get("key")``), else None."""
    if isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant) and isinstance(node.slice.value, str):
        return node.slice.value if holder(node.value) in SETTINGS else None
    if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get" and node.args
            and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
        return node.args[0].value if holder(node.func.value) in SETTINGS else None
    return None


def raw_config_names(node: ast.FunctionDef) -> set[str]:
    """The parameters of a function annotated as a raw config (``DictConfig``)."""
    arguments = [*node.args.posonlyargs, *node.args.args, *node.args.kwonlyargs]
    return {arg.arg for arg in arguments if arg.annotation is not None and "DictConfig" in ast.unparse(arg.annotation)}


def selects(node: ast.AST) -> bool:
    """Whether ``node`` reads a raw config by a dotted key: ``OmegaConf.select(cfg, "a.b")``."""
    return (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "select"
            and isinstance(node.func.value, ast.Name) and node.func.value.id == "OmegaConf")


class Reads(ast.NodeVisitor):
    """The raw reads of settings in a module, counted by the function they are in (its innermost): by key
    (``x["key"]``, ``x.get("key")`` on a settings name), by attribute on a parameter annotated ``DictConfig``
    (``cfg.train``), and by ``OmegaConf.select``."""

    def __init__(self, module: str) -> None:
        self.module, self.functions, self.found = module, [""], Counter[str]()
        self.raw: list[set[str]] = [set()]

    def visit_FunctionDef(self, node: ast.FunctionDef) -> None:
        self.functions.append(node.name)
        self.raw.append(raw_config_names(node))
        self.generic_visit(node)
        self.raw.pop()
        self.functions.pop()

    def generic_visit(self, node: ast.AST) -> None:
        attribute_read = (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                          and node.value.id in self.raw[-1])
        if read_key(node) is not None or attribute_read or selects(node):
            self.found[f"{self.module}:{self.functions[-1]}"] += 1
        super().generic_visit(node)


def reads_by_key() -> Counter[str]:
    """'module.py:function' -> the settings it reads by key, for every module below the commands."""
    found: Counter[str] = Counter()
    for path in sorted(PACKAGE.rglob("*.py")):
        module = path.relative_to(PACKAGE).as_posix()
        if "/" not in module and path.stem in COMMANDS:
            continue
        reads = Reads(module)
        reads.visit(ast.parse(path.read_text()))
        found.update(reads.found)
    return found


def excused(place: str) -> bool:
    module = place.split(":")[0]
    return place in BOUNDARIES or module in BOUNDARIES or module.split("/")[0] in BOUNDARIES


def test_no_setting_is_read_by_key_below_the_commands():
    reads = reads_by_key()
    offending = {place: count for place, count in reads.items() if not excused(place)}
    assert not offending, f"settings read by key (type them where the config is read, pass the instance): {offending}"


def test_the_check_finds_every_form_of_raw_read():
    reads = Reads("m.py")
    source = ('def f(cfg, row):\n    return cfg["train"]["lr"], cfg.get("x"), row["flops"], cfg.train.lr\n'
              'def g(launch: DictConfig, pair: Pair):\n    return launch.train.lr, pair.train.lr\n'
              'def h(values):\n    return OmegaConf.select(values, "budget.stop_when")\n')
    reads.visit(ast.parse(source))
    # f: cfg["train"], cfg["train"]["lr"], cfg.get("x"), not the row's nor an unannotated attribute; g: the
    # DictConfig's attribute, not the typed pair's; h: the select
    assert reads.found == {"m.py:f": 3, "m.py:g": 1, "m.py:h": 1}


def test_no_class_name_is_defined_twice_in_the_package():
    """One name per concept: two classes of one name make every reader ask which one they hold."""
    defined = Counter(node.name for path in PACKAGE.rglob("*.py") for node in ast.walk(ast.parse(path.read_text()))
                      if isinstance(node, ast.ClassDef))
    assert [name for name, count in defined.items() if count > 1] == []
