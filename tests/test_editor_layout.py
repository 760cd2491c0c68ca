"""Every folder the build maps into the namespace (pyproject.toml `package-dir`: `envisat_pose.perception` is the
repository's `perception/`, ...) is also a relative symbolic link inside `envisat_pose/` (`envisat_pose/perception
-> ../perception`), so that static tools that do not run setuptools' import hook (pyright and the editors built on
it, `python -m` in the root without the install) find `envisat_pose.perception.*` on disk. A folder added to the
build without its link fails here; so does a link left behind when a folder is dropped."""

import os
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CORE = os.path.join(ROOT, "envisat_pose")


def mapped_folders() -> dict[str, str]:
    """{subpackage name under envisat_pose: repository folder} from the build's package-dir."""
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as fh:
        package_dir = tomllib.load(fh)["tool"]["setuptools"]["package-dir"]
    return {name.split(".", 1)[1]: folder for name, folder in package_dir.items() if name.startswith("envisat_pose.")}


def test_every_mapped_folder_has_its_link():
    folders = mapped_folders()
    assert {"datagen", "perception", "filtering", "analysis", "pipelines", "app"} <= set(folders)
    for name, folder in folders.items():
        link = os.path.join(CORE, name)
        assert os.path.islink(link), f"envisat_pose/{name} is not a link to ../{folder} (ln -s ../{folder} {link})"
        assert os.readlink(link) == os.path.join("..", folder), f"envisat_pose/{name} -> {os.readlink(link)}"
        assert os.path.samefile(link, os.path.join(ROOT, folder))


def test_no_link_without_its_folder():
    links = {n for n in os.listdir(CORE) if os.path.islink(os.path.join(CORE, n))}
    assert links == set(mapped_folders()), sorted(links ^ set(mapped_folders()))


def test_a_mapped_module_is_the_same_file_by_either_path():
    import envisat_pose.perception.model as model

    here = os.path.realpath(model.__file__)
    assert here == os.path.realpath(os.path.join(ROOT, "perception", "model.py"))
