"""The sockets a process can be reached on, read from /proc (Linux): listening TCP and
unconnected UDP sockets with their bound address."""

from __future__ import annotations

import ipaddress
import os
from pathlib import Path

TCP_LISTEN = "0A"


def _inodes(pid: int) -> set[str]:
    out = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            link = os.readlink(fd)
        except OSError:
            continue
        if link.startswith("socket:["):
            out.add(link[8:-1])
    return out


def _address(hex_ip: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address:
    raw = bytes.fromhex(hex_ip)
    # /proc/net writes each 32-bit word in host (little-endian) order
    words = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
    ip = ipaddress.ip_address(words)
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped:
        return ip.ipv4_mapped
    return ip


def reachable(pid: int) -> list[tuple[str, str, int]]:
    """(protocol, address, port) of every socket of ``pid`` another host could send to."""
    inodes = _inodes(pid)
    out = []
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        try:
            lines = Path(f"/proc/{pid}/net/{proto}").read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            local, remote, state, inode = f[1], f[2], f[3], f[9]
            if inode not in inodes:
                continue
            if proto.startswith("tcp") and state != TCP_LISTEN:
                continue
            if proto.startswith("udp") and int(remote.split(":")[1], 16) != 0:
                continue  # connected: answers from its peer only
            ip, port = local.split(":")
            out.append((proto, str(_address(ip)), int(port, 16)))
    return out


def beyond_loopback(pid: int) -> list[tuple[str, str, int]]:
    return [s for s in reachable(pid) if not ipaddress.ip_address(s[1]).is_loopback]
