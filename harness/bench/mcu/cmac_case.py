"""The CMAC case of `rhonn-bench mcu` (``--case harness.bench.mcu.cmac_case:cmac_case``): the
node's AES-128-CMAC (controller/native/node/node_cmac.c) on the Cortex-M4F, one SecOC MAC
input per step, against the ``cryptography`` package's CMAC; the instructions per step are
one CMAC of 18 bytes (two AES blocks) plus the step's own few (index in, 16 bytes out)."""

from __future__ import annotations

import random

import numpy as np
from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.cmac import CMAC

from controller.native.build_tools import NATIVE_DIR
from harness.bench.mcu.case import MCU_DIR, McuCase

NODE_DIR = NATIVE_DIR / "node"
MESSAGE_BYTES = 18  # SecOC MAC input: ID (2 bytes) || payload (8) || FV (8), can_db/secoc.py


def _c_bytes(name: str, rows: list[bytes]) -> str:
    body = ",\n".join("  {" + ", ".join(f"0x{b:02X}u" for b in r) + "}" for r in rows)
    return f"static const uint8_t {name}[{len(rows)}][{len(rows[0])}] = {{\n{body}}};\n"


def cmac_case(n_steps: int = 50, seed: int = 0) -> McuCase:
    """``n_steps`` seeded random 18-byte messages under one seeded random key; the expected
    tags are ``cryptography``'s AES-128-CMAC, compared exactly (bound 0)."""
    rng = random.Random(seed)
    key = rng.randbytes(16)
    messages = [rng.randbytes(MESSAGE_BYTES) for _ in range(n_steps)]
    tags = []
    for m in messages:
        mac = CMAC(algorithms.AES(key))
        mac.update(m)
        tags.append(list(mac.finalize()))
    config = (
        "#include <stdint.h>\n"
        f"#define MCU_CMAC_MESSAGE_BYTES {MESSAGE_BYTES}u\n"
        + "static const uint8_t MCU_CMAC_KEY[16] = {"
        + ", ".join(f"0x{b:02X}u" for b in key)
        + "};\n"
        + _c_bytes("MCU_CMAC_MESSAGES", messages)
    )
    expected = np.asarray(tags, dtype=np.float32)
    return McuCase(
        name="node AES-128-CMAC (node_cmac.c), 18-byte SecOC MAC inputs",
        adapter=MCU_DIR / "cases" / "node_cmac.c",
        sources=[NODE_DIR / "node_cmac.c"],
        config_c=config,
        inputs=np.arange(n_steps, dtype=np.float32)[:, None],
        expected=expected,
        tolerance=np.zeros_like(expected),
        bound_text="exact: every tag byte equals cryptography's AES-128-CMAC",
        output_names=[f"tag{k}" for k in range(16)],
        include_dirs=[NODE_DIR],
    )
