"""Helpers for the ROS tests: which UDP addresses a process has bound, and a raw subscriber
that records everything it receives."""
from __future__ import annotations

import os
import socket
import struct
import time
from collections import defaultdict


def udp_local_addresses(pid: int) -> set[str]:
    """'ip:port' of every UDP (v4 and v6) socket the process holds, read from /proc."""
    inodes = set()
    fd_dir = f"/proc/{pid}/fd"
    for fd in os.listdir(fd_dir):
        try:
            target = os.readlink(os.path.join(fd_dir, fd))
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    addresses = set()
    for table, family in (("udp", socket.AF_INET), ("udp6", socket.AF_INET6)):
        try:
            lines = open(f"/proc/{pid}/net/{table}").read().splitlines()[1:]
        except FileNotFoundError:
            continue
        for line in lines:
            fields = line.split()
            if fields[9] not in inodes:
                continue
            hex_ip, hex_port = fields[1].split(":")
            raw = bytes.fromhex(hex_ip)
            if family == socket.AF_INET:
                ip = socket.inet_ntop(family, struct.pack("<I", int(hex_ip, 16)))
            else:  # four little-endian 32-bit words
                ip = socket.inet_ntop(family, b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4)))
            addresses.add(f"{ip}:{int(hex_port, 16)}")
    return addresses


def non_loopback(addresses: set[str]) -> set[str]:
    return {a for a in addresses if not (a.startswith("127.") or a.startswith("::1:"))}


class RawRecorder:
    """Subscribes to topics and keeps (receive time, raw CDR bytes) per topic."""

    def __init__(self, node, topics: dict[str, tuple[type, object]]):
        self.received = defaultdict(list)
        self.subscriptions = [
            node.create_subscription(cls, topic, self._callback(topic), qos, raw=True)
            for topic, (cls, qos) in topics.items()]

    def _callback(self, topic):
        def store(raw):
            self.received[topic].append((time.monotonic(), bytes(raw)))
        return store

    def counts(self) -> dict[str, int]:
        return {topic: len(items) for topic, items in self.received.items()}
