"""XXH3-128 (seed 0, default secret) in pure Python: the hash rmw_zenoh makes its gids with.

rmw_zenoh_cpp hashes every entity's liveliness token with `simplified_XXH3_128bits`
(rmw_zenoh_cpp/src/detail/simplified_xxhash3.cpp, the portable scalar code of xxHash,
https://github.com/Cyan4973/xxHash, BSD-2-Clause, Yann Collet). This is the same algorithm,
branch for branch (0-16, 17-128, 129-240 bytes and the long-input loop); tokens are hashed
once per publisher, so speed does not matter.
"""

from __future__ import annotations

import struct

_MASK64 = (1 << 64) - 1
_PRIME32_1, _PRIME32_2, _PRIME32_3 = 0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D
_PRIME64_1, _PRIME64_2, _PRIME64_3 = 0x9E3779B185EBCA87, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9
_PRIME64_4, _PRIME64_5 = 0x85EBCA77C2B2AE63, 0x27D4EB2F165667C5
_PRIME_MX1, _PRIME_MX2 = 0x165667919E3779F9, 0x9FB21C651E98DF25
_STRIPE_LEN, _SECRET_CONSUME_RATE, _ACC_NB = 64, 8, 8
_SECRET_SIZE_MIN, _MIDSIZE_MAX = 136, 240
_MIDSIZE_STARTOFFSET, _MIDSIZE_LASTOFFSET = 3, 17
_SECRET_LASTACC_START, _SECRET_MERGEACCS_START = 7, 11
_SECRET = bytes.fromhex(
    "b8fe6c3923a44bbe7c01812cf721ad1cded46de9839097db7240a4a4b7b3671f"
    "cb79e64eccc0e578825ad07dccff7221b8084674f743248ee03590e6813a264c"
    "3c2852bb91c300cb88d0658b1b532ea371644897a20df94e3819ef46a9deacd8"
    "a8fa763fe39c343ff9dcbbc7c70b4f1d8a51e04bcdb45931c89f7ec9d9787364"
    "eac5ac8334d3ebc3c581a0fffa1363eb170ddd51b7f0da49d316552629d4689e"
    "2b16be587d47a1fc8ff8b8d17ad031ce45cb3a8f95160428afd7fbcabb4b407e"
)  # XXH3_kSecret, 192 bytes


def xxh3_128(data: bytes) -> tuple[int, int]:
    """(low64, high64) of XXH3_128bits(`data`) with seed 0."""
    n = len(data)
    if n <= 16:
        return _len_0to16(data, n)
    if n <= 128:
        return _len_17to128(data, n)
    if n <= _MIDSIZE_MAX:
        return _len_129to240(data, n)
    return _hash_long(data, n)


def xxh3_128_digest(data: bytes) -> bytes:
    """The 16 bytes rmw_zenoh copies into a gid: low64 then high64, each little-endian."""
    low, high = xxh3_128(data)
    return struct.pack("<QQ", low, high)


def _le64(data: bytes, offset: int) -> int:
    return int.from_bytes(data[offset : offset + 8], "little")


def _le32(data: bytes, offset: int) -> int:
    return int.from_bytes(data[offset : offset + 4], "little")


def _mult64to128(lhs: int, rhs: int) -> tuple[int, int]:
    product = (lhs & _MASK64) * (rhs & _MASK64)
    return product & _MASK64, product >> 64


def _mul128_fold64(lhs: int, rhs: int) -> int:
    low, high = _mult64to128(lhs, rhs)
    return low ^ high


def _xorshift64(value: int, shift: int) -> int:
    return value ^ (value >> shift)


def _avalanche(h64: int) -> int:
    h64 = _xorshift64(h64, 37)
    h64 = (h64 * _PRIME_MX1) & _MASK64
    return _xorshift64(h64, 32)


def _xxh64_avalanche(h64: int) -> int:
    h64 ^= h64 >> 33
    h64 = (h64 * _PRIME64_2) & _MASK64
    h64 ^= h64 >> 29
    h64 = (h64 * _PRIME64_3) & _MASK64
    return h64 ^ (h64 >> 32)


def _swap64(value: int) -> int:
    return int.from_bytes(value.to_bytes(8, "little"), "big")


def _swap32(value: int) -> int:
    return int.from_bytes(value.to_bytes(4, "little"), "big")


def _rotl32(value: int, bits: int) -> int:
    return ((value << bits) | (value >> (32 - bits))) & 0xFFFFFFFF


def _len_1to3(data: bytes, n: int) -> tuple[int, int]:
    c1, c2, c3 = data[0], data[n >> 1], data[n - 1]
    combined_low = (c1 << 16) | (c2 << 24) | c3 | (n << 8)
    combined_high = _rotl32(_swap32(combined_low), 13)
    bitflip_low = _le32(_SECRET, 0) ^ _le32(_SECRET, 4)
    bitflip_high = _le32(_SECRET, 8) ^ _le32(_SECRET, 12)
    return (
        _xxh64_avalanche(combined_low ^ bitflip_low),
        _xxh64_avalanche(combined_high ^ bitflip_high),
    )


def _len_4to8(data: bytes, n: int) -> tuple[int, int]:
    input_64 = _le32(data, 0) + (_le32(data, n - 4) << 32)
    keyed = input_64 ^ (_le64(_SECRET, 16) ^ _le64(_SECRET, 24))
    low, high = _mult64to128(keyed, (_PRIME64_1 + (n << 2)) & _MASK64)
    high = (high + (low << 1)) & _MASK64
    low ^= high >> 3
    low = _xorshift64(low, 35)
    low = (low * _PRIME_MX2) & _MASK64
    low = _xorshift64(low, 28)
    return low, _avalanche(high)


def _len_9to16(data: bytes, n: int) -> tuple[int, int]:
    bitflip_low = _le64(_SECRET, 32) ^ _le64(_SECRET, 40)
    bitflip_high = _le64(_SECRET, 48) ^ _le64(_SECRET, 56)
    input_low, input_high = _le64(data, 0), _le64(data, n - 8)
    m_low, m_high = _mult64to128(input_low ^ input_high ^ bitflip_low, _PRIME64_1)
    m_low = (m_low + ((n - 1) << 54)) & _MASK64
    input_high ^= bitflip_high
    m_high = (m_high + input_high + (input_high & 0xFFFFFFFF) * (_PRIME32_2 - 1)) & _MASK64
    m_low ^= _swap64(m_high)
    h_low, h_high = _mult64to128(m_low, _PRIME64_2)
    h_high = (h_high + m_high * _PRIME64_2) & _MASK64
    return _avalanche(h_low), _avalanche(h_high)


def _len_0to16(data: bytes, n: int) -> tuple[int, int]:
    if n > 8:
        return _len_9to16(data, n)
    if n >= 4:
        return _len_4to8(data, n)
    if n:
        return _len_1to3(data, n)
    bitflip_low = _le64(_SECRET, 64) ^ _le64(_SECRET, 72)
    bitflip_high = _le64(_SECRET, 80) ^ _le64(_SECRET, 88)
    return _xxh64_avalanche(bitflip_low), _xxh64_avalanche(bitflip_high)


def _mix16(data: bytes, offset: int, secret_offset: int) -> int:
    return _mul128_fold64(
        _le64(data, offset) ^ _le64(_SECRET, secret_offset),
        _le64(data, offset + 8) ^ _le64(_SECRET, secret_offset + 8),
    )


def _mix32(
    acc: tuple[int, int], data: bytes, offset_1: int, offset_2: int, secret_offset: int
) -> tuple[int, int]:
    low, high = acc
    low = (low + _mix16(data, offset_1, secret_offset)) & _MASK64
    low ^= (_le64(data, offset_2) + _le64(data, offset_2 + 8)) & _MASK64
    high = (high + _mix16(data, offset_2, secret_offset + 16)) & _MASK64
    high ^= (_le64(data, offset_1) + _le64(data, offset_1 + 8)) & _MASK64
    return low, high


def _finish_mid(acc: tuple[int, int], n: int) -> tuple[int, int]:
    low, high = acc
    h_low = (low + high) & _MASK64
    h_high = (low * _PRIME64_1 + high * _PRIME64_4 + n * _PRIME64_2) & _MASK64
    return _avalanche(h_low), (-_avalanche(h_high)) & _MASK64


def _len_17to128(data: bytes, n: int) -> tuple[int, int]:
    acc = ((n * _PRIME64_1) & _MASK64, 0)
    if n > 32:
        if n > 64:
            if n > 96:
                acc = _mix32(acc, data, 48, n - 64, 96)
            acc = _mix32(acc, data, 32, n - 48, 64)
        acc = _mix32(acc, data, 16, n - 32, 32)
    acc = _mix32(acc, data, 0, n - 16, 0)
    return _finish_mid(acc, n)


def _len_129to240(data: bytes, n: int) -> tuple[int, int]:
    acc = ((n * _PRIME64_1) & _MASK64, 0)
    for i in range(32, 160, 32):
        acc = _mix32(acc, data, i - 32, i - 16, i - 32)
    acc = (_avalanche(acc[0]), _avalanche(acc[1]))
    for i in range(160, n + 1, 32):
        acc = _mix32(acc, data, i - 32, i - 16, _MIDSIZE_STARTOFFSET + i - 160)
    acc = _mix32(acc, data, n - 16, n - 32, _SECRET_SIZE_MIN - _MIDSIZE_LASTOFFSET - 16)
    return _finish_mid(acc, n)


def _accumulate_512(acc: list[int], data: bytes, offset: int, secret_offset: int) -> None:
    for lane in range(_ACC_NB):
        value = _le64(data, offset + lane * 8)
        key = value ^ _le64(_SECRET, secret_offset + lane * 8)
        acc[lane ^ 1] = (acc[lane ^ 1] + value) & _MASK64
        acc[lane] = ((key & 0xFFFFFFFF) * (key >> 32) + acc[lane]) & _MASK64


def _scramble(acc: list[int], secret_offset: int) -> None:
    for lane in range(_ACC_NB):
        value = _xorshift64(acc[lane], 47) ^ _le64(_SECRET, secret_offset + lane * 8)
        acc[lane] = (value * _PRIME32_1) & _MASK64


def _accumulate(acc: list[int], data: bytes, offset: int, n_stripes: int) -> None:
    for stripe in range(n_stripes):
        _accumulate_512(acc, data, offset + stripe * _STRIPE_LEN, stripe * _SECRET_CONSUME_RATE)


def _merge(acc: list[int], secret_offset: int, start: int) -> int:
    result = start
    for i in range(4):
        result += _mul128_fold64(
            acc[2 * i] ^ _le64(_SECRET, secret_offset + 16 * i),
            acc[2 * i + 1] ^ _le64(_SECRET, secret_offset + 16 * i + 8),
        )
    return _avalanche(result & _MASK64)


def _hash_long(data: bytes, n: int) -> tuple[int, int]:
    acc = [
        _PRIME32_3, _PRIME64_1, _PRIME64_2, _PRIME64_3, _PRIME64_4, _PRIME32_2, _PRIME64_5,
        _PRIME32_1,
    ]  # fmt: skip
    stripes_per_block = (len(_SECRET) - _STRIPE_LEN) // _SECRET_CONSUME_RATE
    block_len = _STRIPE_LEN * stripes_per_block
    n_blocks = (n - 1) // block_len
    for block in range(n_blocks):
        _accumulate(acc, data, block * block_len, stripes_per_block)
        _scramble(acc, len(_SECRET) - _STRIPE_LEN)
    n_stripes = ((n - 1) - block_len * n_blocks) // _STRIPE_LEN
    _accumulate(acc, data, n_blocks * block_len, n_stripes)
    _accumulate_512(acc, data, n - _STRIPE_LEN, len(_SECRET) - _STRIPE_LEN - _SECRET_LASTACC_START)
    low = _merge(acc, _SECRET_MERGEACCS_START, (n * _PRIME64_1) & _MASK64)
    high = _merge(
        acc,
        len(_SECRET) - _ACC_NB * 8 - _SECRET_MERGEACCS_START,
        ~(n * _PRIME64_2) & _MASK64,
    )
    return low, high
