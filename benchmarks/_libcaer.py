"""libcaer's DAVIS event translator as the decoder benchmark's reference, built from a user's libcaer checkout.

Nothing of libcaer is kept in this repository. :func:`build_translator` compiles ``libcaer_translator.c`` (the
harness beside this file) together with the checkout's ``src/davis_common.h`` (libcaer's DAVIS host logic,
``davisCommonEventTranslator`` included) and the few sources it links against, with the system C compiler and
libcaer's own Release settings (``-O3 -DNDEBUG -std=gnu11``, its POSIX defines). The only generated header is
``libcaer.h``, configured from the checkout's ``libcaer.h.in`` as CMake would (version from its
``CMakeLists.txt``, serial-device and OpenCV support off). :class:`LibcaerTranslator` runs a byte stream through
the translator, one call per transfer as libcaer's USB thread does, via ctypes.
"""

from __future__ import annotations

import ctypes
import re
import shutil
import subprocess
from pathlib import Path
from typing import NamedTuple

HARNESS = Path(__file__).with_name("libcaer_translator.c")
#: Sources of the checkout's src/ that davis_common.h needs at link time (logging, ring buffer, its helpers).
LINKED_SOURCES = ("log.c", "ringbuffer.c", "autoexposure.c", "filters_dvs_noise.c", "frame_utils.c")
#: libcaer's CMake Release build: optimisation, C standard (CMAKE_C_STANDARD 11, extensions on), POSIX defines.
CFLAGS = ("-O3", "-DNDEBUG", "-std=gnu11", "-fPIC", "-shared", "-pthread", "-DOS_UNIX=1", "-DOS_LINUX=1",
          "-DHAVE_PTHREADS=1", "-D_XOPEN_SOURCE=700", "-D_DEFAULT_SOURCE=1", "-D_FILE_OFFSET_BITS=64")


class LibcaerRun(NamedTuple):
    """One stream through libcaer's translator.

    Attributes:
        polarity_events: DVS events in the packets produced.
        special_events: special events in the packets produced.
        translator_s: seconds inside the translator calls (CLOCK_MONOTONIC), without draining the packets.
    """

    polarity_events: int
    special_events: int
    translator_s: float


def libcaer_version(src: Path) -> str:
    """The version in the checkout's top-level CMakeLists.txt (``PROJECT(libcaer VERSION x.y.z ...)``).

    Raises:
        ValueError: no version found there.
    """
    match = re.search(r"PROJECT\s*\(\s*libcaer\s+VERSION\s+(\d+)\.(\d+)\.(\d+)", (src / "CMakeLists.txt").read_text(),
                      re.IGNORECASE)
    if match is None:
        raise ValueError(f"{src / 'CMakeLists.txt'}: no 'PROJECT(libcaer VERSION x.y.z' line")
    return ".".join(match.groups())


def build_translator(src: Path, build_dir: Path, cc: str = "cc") -> Path:
    """Compile libcaer's translator and the harness into a shared library in ``build_dir``; return its path.

    Args:
        src: root of a libcaer source checkout (with ``src/davis_common.h`` and ``include/libcaer/libcaer.h.in``).
        build_dir: an empty or scratch folder for the configured headers and the library.
        cc: the C compiler.

    Raises:
        ValueError: ``src`` is not a libcaer checkout.
        RuntimeError: the compiler failed (its output is in the message).
    """
    src = Path(src)
    needed = [src / "src" / "davis_common.h", src / "include" / "libcaer" / "libcaer.h.in", src / "CMakeLists.txt"]
    needed += [src / "src" / name for name in LINKED_SOURCES]
    missing = [str(p) for p in needed if not p.is_file()]
    if missing:
        raise ValueError(f"{src}: not a libcaer source checkout (missing {', '.join(missing)})")
    major, minor, patch = libcaer_version(src).split(".")
    include = Path(build_dir) / "include"
    shutil.rmtree(include, ignore_errors=True)
    # the headers include "../libcaer.h" relative to themselves: the configured header goes beside a copy of them
    shutil.copytree(src / "include" / "libcaer", include / "libcaer")
    header = (src / "include" / "libcaer" / "libcaer.h.in").read_text()
    for key, value in {"PROJECT_VERSION_MAJOR": major, "PROJECT_VERSION_MINOR": minor,
                       "PROJECT_VERSION_PATCH": patch, "PROJECT_NAME": "libcaer",
                       "PROJECT_VERSION": f"{major}.{minor}.{patch}"}.items():
        header = header.replace(f"@{key}@", value)
    header = re.sub(r"#cmakedefine01 (\w+)", r"#define \1 0", header)
    (include / "libcaer" / "libcaer.h").write_text(header)
    library = Path(build_dir) / "libcaer_translator.so"
    command = [cc, *CFLAGS, f"-I{include}", f"-I{src / 'src'}", str(HARNESS),
               *(str(src / "src" / name) for name in LINKED_SOURCES), "-lm", "-o", str(library)]
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        raise RuntimeError(f"building libcaer's translator failed ({' '.join(command)}):\n{result.stderr[-4000:]}")
    return library


class LibcaerTranslator:
    """ctypes handle on a library made by :func:`build_translator`."""

    def __init__(self, library: Path):
        self._lib = ctypes.CDLL(str(library))
        self._lib.lc_run.argtypes = [ctypes.c_char_p, ctypes.c_size_t, ctypes.c_size_t,
                                     ctypes.POINTER(ctypes.c_int64)]
        self._lib.lc_run.restype = ctypes.c_int
        self._out = (ctypes.c_int64 * 3)()

    def run(self, data: bytes, transfer_bytes: int) -> LibcaerRun:
        """Translate ``data`` with a fresh handle, ``transfer_bytes`` per translator call (the last may be shorter).

        Raises:
            MemoryError: libcaer could not allocate its state.
        """
        if self._lib.lc_run(data, len(data), transfer_bytes, self._out) != 0:
            raise MemoryError("libcaer could not allocate its device state")
        return LibcaerRun(int(self._out[0]), int(self._out[1]), self._out[2] * 1e-9)
