"""Detect the Vulkan device SAPIEN renders with, and explain how to get one."""
from __future__ import annotations

import contextlib
import io

#: The exact commands that give a Debian 12 machine a Vulkan device SAPIEN accepts.
VULKAN_FIX = (
    "SAPIEN found no usable Vulkan device. On Debian 12, install Mesa 25 (lavapipe) from "
    "bookworm-backports as root:\n"
    "  printf 'Types: deb\\nURIs: http://deb.debian.org/debian\\nSuites: bookworm-backports\\n"
    "Components: main\\nSigned-By: /usr/share/keyrings/debian-archive-keyring.gpg\\n' "
    "> /etc/apt/sources.list.d/backports.sources\n"
    "  apt-get update && apt-get install -y -t bookworm-backports mesa-vulkan-drivers libvulkan1\n"
    "(or run scripts/setup.sh as root, which does this). Debian's own Mesa 22 lacks the "
    "descriptorBindingPartiallyBound feature SAPIEN needs."
)


class VulkanUnavailableError(RuntimeError):
    """SAPIEN cannot find a Vulkan device to render (or even simulate) with."""

    def __init__(self, detail: str = ""):
        msg = VULKAN_FIX if not detail else f"{VULKAN_FIX}\n(SAPIEN said: {detail.strip()})"
        super().__init__(msg)


def device_summary() -> str:
    """SAPIEN's own description of the render devices it sees."""
    import sapien

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        summary = sapien.render.get_device_summary()
    return summary or buf.getvalue()


def supported_device_name() -> str | None:
    """Name of the first device SAPIEN reports as supported, else ``None``."""
    try:
        summary = device_summary()
    except Exception:  # noqa: BLE001 - any failure here means "no device"
        return None
    name = None
    for line in summary.splitlines():
        line = line.strip()
        if line.startswith("GPU:"):
            name = line[len("GPU:"):].strip()
        elif line.startswith("Supported:") and line.split(":")[1].strip() == "1" and name:
            return name
    return None


def is_render_device_error(err: BaseException) -> bool:
    """Whether ``err`` is SAPIEN's way of saying it has no usable Vulkan device."""
    text = str(err).lower()
    return any(
        needle in text
        for needle in ("rendering device", "vulkan", "errorfeaturenotpresent", "errorincompatibledriver")
    )
