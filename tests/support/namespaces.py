"""Network namespaces as separate hosts for the multi-host tests: each namespace has its own interfaces and
addresses, linked to a hub namespace by a virtual ethernet pair, so processes in different namespaces reach each
other only over those links, which a test can cut (`partition`) like a network failure. Needs root and `ip`;
`why_not` says why namespaces cannot be made here."""

from __future__ import annotations

import os
import shutil
import subprocess
import uuid
from dataclasses import dataclass, field


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True)


def why_not() -> str | None:
    """None when this machine lets the test make namespaces, else the reason."""
    if shutil.which("ip") is None:
        return "the `ip` tool (iproute2) is not installed"
    if os.geteuid() != 0:
        return "making network namespaces needs root"
    probe = f"impulse-probe-{uuid.uuid4().hex[:6]}"
    made = _ip("netns", "add", probe)
    if made.returncode != 0:
        return f"`ip netns add` failed: {made.stderr.strip()}"
    _ip("netns", "del", probe)
    return None


@dataclass
class Hosts:
    """A hub namespace and spoke namespaces, spoke i reaching the hub at 10.<net>.<i+1>.1 from 10.<net>.<i+1>.2.
    Spoke "here" is the test's own (root) namespace, so the test's processes can reach the hub too."""

    net: int = 79
    tag: str = field(default_factory=lambda: uuid.uuid4().hex[:6])
    spokes: dict[str, int] = field(default_factory=dict)
    made: list[str] = field(default_factory=list)

    @property
    def hub(self) -> str:
        return f"imp-{self.tag}-hub"

    def namespace(self, name: str) -> str:
        return f"imp-{self.tag}-{name}"

    def hub_address(self, spoke: str) -> str:
        """The hub's address as `spoke` reaches it."""
        return f"10.{self.net}.{self.spokes[spoke] + 1}.1"

    def _run(self, *args: str) -> None:
        done = _ip(*args)
        if done.returncode != 0:
            raise RuntimeError(f"ip {' '.join(args)}: {done.stderr.strip()}")

    def create(self, spokes: list[str]) -> None:
        self._run("netns", "add", self.hub)
        self.made.append(self.hub)
        self._run("-n", self.hub, "link", "set", "lo", "up")
        for index, spoke in enumerate(spokes):
            self.spokes[spoke] = index
            hub_end, spoke_end = f"ih{self.tag}{index}", f"is{self.tag}{index}"
            subnet = f"10.{self.net}.{index + 1}"
            self._run("link", "add", hub_end, "type", "veth", "peer", "name", spoke_end)
            self._run("link", "set", hub_end, "netns", self.hub)
            self._run("-n", self.hub, "addr", "add", f"{subnet}.1/24", "dev", hub_end)
            self._run("-n", self.hub, "link", "set", hub_end, "up")
            if spoke == "here":
                self._run("addr", "add", f"{subnet}.2/24", "dev", spoke_end)
                self._run("link", "set", spoke_end, "up")
                continue
            namespace = self.namespace(spoke)
            self._run("netns", "add", namespace)
            self.made.append(namespace)
            self._run("-n", namespace, "link", "set", "lo", "up")
            self._run("link", "set", spoke_end, "netns", namespace)
            self._run("-n", namespace, "addr", "add", f"{subnet}.2/24", "dev", spoke_end)
            self._run("-n", namespace, "link", "set", spoke_end, "up")

    def prefix(self, spoke: str | None) -> list[str]:
        """Command prefix that runs a program in `spoke`'s namespace (None or "here": the hub's own is `hub`)."""
        if spoke == "hub":
            return ["ip", "netns", "exec", self.hub]
        return ["ip", "netns", "exec", self.namespace(spoke)] if spoke not in (None, "here") else []

    def partition(self, spoke: str, connected: bool) -> None:
        """Cut (or restore) `spoke`'s link to the hub, from the hub's side."""
        self._run("-n", self.hub, "link", "set", f"ih{self.tag}{self.spokes[spoke]}", "up" if connected else "down")

    def destroy(self) -> None:
        for spoke, index in self.spokes.items():
            if spoke == "here":
                _ip("link", "del", f"is{self.tag}{index}")
        for namespace in reversed(self.made):
            _ip("netns", "del", namespace)
