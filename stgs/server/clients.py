"""Who a request comes from: the peer address, or behind a trusted proxy the address the proxy forwarded.

The per-client limits key on this address. `X-Forwarded-For` and `Forwarded` are believed only from a peer in
one of the trusted ranges (`--trusted-proxy CIDR`); from anyone else they are ignored, since any client can send
them. The forwarded chain is read from the right (the hop nearest to us) past every trusted address: the first
untrusted one is the client, as nginx's real_ip_recursive does; a chain of only trusted addresses gives its
leftmost."""

from __future__ import annotations

import ipaddress
import re
from collections.abc import Iterable, Mapping

from stgs.errors import FieldError

Network = ipaddress.IPv4Network | ipaddress.IPv6Network

_FORWARDED_FOR = re.compile(r'(?:^|[;,\s])for\s*=\s*("?)([^";,\s]+)\1', re.IGNORECASE)


def trusted_networks(cidrs: Iterable[str]) -> tuple[Network, ...]:
    """The ranges of `cidrs` (addresses or CIDR blocks); a malformed one is an error naming the setting."""
    out = []
    for cidr in cidrs:
        try:
            out.append(ipaddress.ip_network(cidr.strip(), strict=False))
        except ValueError:
            raise FieldError("trusted_proxies", f"{cidr!r} is not an address or CIDR range") from None
    return tuple(out)


def _address(token: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    """An address from one forwarded token: `1.2.3.4`, `1.2.3.4:5678`, `[2001:db8::1]:80` or `2001:db8::1`."""
    token = token.strip().strip('"')
    if token.startswith("["):
        token = token[1:].split("]", 1)[0]
    elif token.count(":") == 1:
        token = token.split(":", 1)[0]
    try:
        return ipaddress.ip_address(token)
    except ValueError:
        return None


def forwarded_chain(headers: Mapping[str, str]) -> list[str]:
    """The forwarded addresses, client first: `Forwarded`'s for= values (RFC 7239), else `X-Forwarded-For`'s."""
    forwarded = headers.get("Forwarded")
    if forwarded:
        return [m.group(2) for m in _FORWARDED_FOR.finditer(forwarded)]
    xff = headers.get("X-Forwarded-For")
    return [part for part in xff.split(",") if part.strip()] if xff else []


def client_address(peer: str, headers: Mapping[str, str], trusted: tuple[Network, ...]) -> str:
    """The address the per-client limits count for a request from `peer` with `headers`."""
    if not trusted or not _trusted(_address(peer), trusted):
        return peer
    chain = [_address(token) for token in forwarded_chain(headers)]
    if not chain or any(a is None for a in chain):  # absent or malformed: the proxy itself is the client
        return peer
    for address in reversed(chain):
        if not _trusted(address, trusted):
            return str(address)
    return str(chain[0])


def _trusted(address: ipaddress.IPv4Address | ipaddress.IPv6Address | None, trusted: tuple[Network, ...]) -> bool:
    return address is not None and any(address in net for net in trusted)
