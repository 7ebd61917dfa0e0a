"""What seed 002's replay runs: its ciphers, computers and sensors, by key and label."""

from __future__ import annotations

CIPHERS = ("plain", "3des", "aes", "blowfish", "aes-gcm", "chacha20")
LABELS = {"plain": "plain (nodes copy)", "3des": "3DES-CBC", "aes": "AES-192-CBC", "blowfish": "Blowfish-CBC",
          "aes-gcm": "AES-128-GCM", "chacha20": "ChaCha20-Poly1305"}
PAPER_NAMES = {"3des": "3DES", "aes": "AES", "blowfish": "Blowfish"}
MACHINES = {"full": "this machine (2 vCPUs, unthrottled)", "atom": "Atom D525 stand-in", "i7": "i7-3612QM stand-in"}
SENSORS = ("laser", "image")

__all__ = ["CIPHERS", "LABELS", "MACHINES", "PAPER_NAMES", "SENSORS"]
