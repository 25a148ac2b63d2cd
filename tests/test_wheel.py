"""The shipped configs and model are package data: a built wheel, installed away from the source
tree, composes every command's config and finds the pretrained HydroNet."""

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_installed_wheel_finds_its_configs_and_model(tmp_path):
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(tmp_path / "dist"), str(ROOT)], check=True, capture_output=True)
    wheel = next((tmp_path / "dist").glob("fishsim-*.whl"))
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)  # a wheel is the installed tree, zipped
    script = (
        "import fishsim, fishsim.config as c\n"
        "from fishsim.fluid.factory import SHIPPED_HYDRONET\n"
        f"assert fishsim.__file__.startswith({str(site)!r}), fishsim.__file__\n"
        "for name in c.ROOTS:\n"
        "    c.load_config(name, ['path=run.h5'] if name == 'render' else [])\n"
        "assert c.load_config('simulate', ['fluid=numerical']).fluid.model == 'numerical'\n"
        "assert SHIPPED_HYDRONET.is_file(), SHIPPED_HYDRONET\n"
        "print('ok')\n"
    )
    # -I -S: isolated, no site processing (so no editable-install finder): only the extracted wheel
    # and the environment's site-packages are importable
    env_site = [p for p in sys.path if p.endswith("site-packages")]
    code = f"import sys; sys.path[:0] = [{str(site)!r}]; sys.path += {env_site!r}\n" + script
    out = subprocess.run([sys.executable, "-I", "-S", "-c", code], cwd=tmp_path, capture_output=True, text=True,
                         check=False)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]
