"""The generated documentation pages stay in step with the code."""

import importlib.util
from pathlib import Path

import o3dreg

DOCS = Path(__file__).resolve().parents[1] / "docs"


def load(name):
    spec = importlib.util.spec_from_file_location(name, DOCS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_public_name_has_an_api_page():
    pages = load("gen_api").render()
    for name in o3dreg.__all__:
        if not name.startswith("_"):
            assert f"{name}.md" in pages
    for name, text in pages.items():
        on_disk = DOCS / "api" / name
        assert on_disk.is_file(), f"docs/api/{name} missing: run python docs/gen_api.py"
        assert on_disk.read_text(encoding="utf-8") == text, (
            f"docs/api/{name} is stale: run python docs/gen_api.py"
        )
    stale = {p.name for p in (DOCS / "api").glob("*.md")} - set(pages)
    assert not stale, f"pages for names that are gone: {sorted(stale)}"


def test_command_line_page_is_current():
    text = load("gen_cli").render()
    assert (DOCS / "cli.md").read_text(encoding="utf-8") == text, (
        "docs/cli.md is stale: run python docs/gen_cli.py"
    )
    for command in ("register", "reconstruct", "demo"):
        assert f"## o3dreg {command}" in text


def test_every_public_function_has_a_docstring():
    missing = [
        n
        for n in o3dreg.__all__
        if not n.startswith("_") and not (getattr(o3dreg, n).__doc__ or "").strip()
    ]
    assert not missing


def test_architecture_picture_is_current_and_names_real_modules():
    gen = load("gen_architecture")
    assert (DOCS / "images" / "architecture.svg").read_text(encoding="utf-8") == gen.render(), (
        "docs/images/architecture.svg is stale: run python docs/gen_architecture.py"
    )
    missing = [m for m in gen.modules() if importlib.util.find_spec(m) is None]
    assert not missing, f"the picture names modules that do not exist: {missing}"


def test_every_dotted_o3dreg_name_in_the_prose_exists():
    # Prose that names a module names one that exists, by its own path (not a moved one, which
    # still imports for users, with a warning).
    import importlib
    import re

    import o3dreg

    pages = [*DOCS.glob("*.md"), DOCS.parent / "README.md"]
    missing = []
    for page in pages:
        for name in set(re.findall(r"`(o3dreg(?:\.[A-Za-z_][A-Za-z0-9_]*)+)", page.read_text())):
            if any(name == old or name.startswith(old + ".") for old in o3dreg.MOVED_MODULES):
                missing.append(f"{page.name}: {name} (moved)")
                continue
            parts = name.split(".")
            for cut in range(len(parts), 0, -1):  # the longest importable prefix
                try:
                    obj = importlib.import_module(".".join(parts[:cut]))
                    break
                except ModuleNotFoundError:
                    continue
            try:
                for attribute in parts[cut:]:
                    obj = getattr(obj, attribute)
            except AttributeError:
                missing.append(f"{page.name}: {name}")
    assert not missing, missing


#: Parameters that mean the same in several public functions, and those functions: one wording
#: each (as Open3D shares its argument texts across functions).
SHARED_PARAMETERS = {
    "source": ("registration_rigid", "registration_elastic", "evaluate_elastic"),
    "target": ("registration_rigid", "registration_elastic", "evaluate_elastic"),
    "mesh": (
        "connected_components",
        "crop_mesh",
        "decimate",
        "keep_largest_components",
        "remove_small_components",
        "smooth_taubin",
    ),
}


def parameter_text(function, name):
    """The numpydoc entry of parameter ``name`` in ``function``'s docstring (type and text)."""
    import inspect
    import re

    doc = inspect.getdoc(function) or ""
    block = doc.split("Parameters\n----------\n", 1)[1]
    block = re.split(r"\n\n[A-Z][a-z]+\n-+\n", block, maxsplit=1)[0]
    for entry in re.split(r"\n(?=\S)", block):
        head, _, body = entry.partition("\n")
        if name in [n.strip() for n in head.split(":")[0].split(",")]:
            return head.split(":", 1)[1].strip(), " ".join(body.split())
    raise AssertionError(f"{function.__name__} documents no parameter {name!r}")


def test_a_shared_parameter_has_one_wording():
    import o3dreg

    for name, functions in SHARED_PARAMETERS.items():
        texts = {parameter_text(getattr(o3dreg, f), name) for f in functions}
        assert len(texts) == 1, (name, texts)
