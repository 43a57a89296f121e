"""Which URLs the player follows: a manifest names URLs (BaseURL, templates) and servers answer with redirects,
and neither may send the player where its user did not point it.

By default the player fetches over http(s) only, from the manifest's host and the hosts the MPD's own BaseURLs
name; never from a link-local address (169.254.0.0/16, fe80::/10: where cloud metadata services answer), and
from loopback only when the manifest itself is on loopback (a remote manifest must not reach services on the
player's machine). Addresses are checked as literals in the URL and again as the names resolve (PolicyResolver),
so a name pointing at a refused address is refused too. Each redirect is checked like any other URL.
"""

from __future__ import annotations

import ipaddress
import socket
from dataclasses import dataclass, field
from urllib.parse import urlsplit

from aiohttp.abc import AbstractResolver, ResolveResult
from aiohttp.resolver import DefaultResolver

SCHEMES = ("http", "https")

Address = ipaddress.IPv4Address | ipaddress.IPv6Address


@dataclass(frozen=True)
class UrlPolicySettings:
    """What the player may fetch besides the manifest's own host."""

    hosts: tuple[str, ...] = ()
    """Further hosts (names or addresses) the player may fetch from, e.g. a CDN the origin redirects to."""
    any_host: bool = False
    """Fetch from any host (the address rules below still hold)."""
    link_local: bool = False
    """Allow link-local addresses (169.254.0.0/16, fe80::/10)."""
    loopback: bool | None = None
    """Allow loopback addresses (None: exactly when the manifest's own host is on loopback)."""


class RefusedUrlError(Exception):
    """A URL (or what its host resolves to) that the policy does not let the player fetch."""


class RefusedAddressError(RefusedUrlError, OSError):
    """Raised from name resolution, which aiohttp expects to fail with an OSError."""


def _address(host: str) -> Address | None:
    try:
        address = ipaddress.ip_address(host.strip("[]").split("%")[0])
    except ValueError:
        return None
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return address.ipv4_mapped
    return address


@dataclass
class UrlPolicy:
    """The policy of one playback, anchored at its manifest URL."""

    manifest_url: str
    settings: UrlPolicySettings = field(default_factory=UrlPolicySettings)

    def __post_init__(self) -> None:
        parts = urlsplit(self.manifest_url)
        self.manifest_host = (parts.hostname or "").lower()
        self.hosts = {self.manifest_host, *(h.lower().strip("[]") for h in self.settings.hosts)}
        literal = _address(self.manifest_host)
        self.loopback = self.settings.loopback
        if self.loopback is None and (self.manifest_host == "localhost" or (literal is not None and
                                                                           literal.is_loopback)):
            self.loopback = True

    def allow_hosts_of(self, *urls: str) -> None:
        """Add the hosts of the manifest's own BaseURLs (http(s) only)."""
        for url in urls:
            parts = urlsplit(url)
            if parts.scheme.lower() in SCHEMES and parts.hostname:
                self.hosts.add(parts.hostname.lower())

    def check(self, url: str) -> None:
        """Raise RefusedUrlError unless the player may fetch `url` (its literal address included)."""
        parts = urlsplit(url)
        if parts.scheme.lower() not in SCHEMES:
            raise RefusedUrlError(f"only http and https URLs are followed, not {parts.scheme or 'a relative'}: URLs")
        host = (parts.hostname or "").lower()
        if not host:
            raise RefusedUrlError("the URL names no host")
        if not self.settings.any_host and host not in self.hosts:
            raise RefusedUrlError(f"host {host} is neither the manifest's nor named by its BaseURLs "
                             "(allow it with --allow-host)")
        literal = _address(host)
        if literal is not None:
            self.check_address(host, literal)

    def check_address(self, host: str, address: Address) -> None:
        if address.is_link_local and not self.settings.link_local:
            raise RefusedAddressError(f"{host} is a link-local address ({address}), refused (--allow-link-local)")
        if address.is_unspecified:
            raise RefusedAddressError(f"{host} is the unspecified address ({address}), refused")
        if address.is_loopback and not self.loopback:
            raise RefusedAddressError(f"{host} is a loopback address ({address}) and the manifest is not on loopback, "
                                 "refused (--allow-loopback)")

    def resolved(self, host: str, results: list[ResolveResult]) -> list[ResolveResult]:
        """The addresses of `host` the player may connect to; the manifest's host resolving to loopback only
        makes loopback allowed (unless the settings say otherwise)."""
        addresses = [(r, _address(r["host"])) for r in results]
        if (host.lower() == self.manifest_host and self.settings.loopback is None
                and addresses and all(a is not None and a.is_loopback for _, a in addresses)):
            self.loopback = True
        kept, refused = [], None
        for result, address in addresses:
            try:
                if address is None:
                    raise RefusedAddressError(f"{host} resolved to {result['host']!r}, not an address")
                self.check_address(host, address)
            except RefusedAddressError as exc:
                refused = exc
                continue
            kept.append(result)
        if not kept:
            raise refused or RefusedAddressError(f"{host} resolved to no address")
        return kept


class PolicyResolver(AbstractResolver):
    """aiohttp's resolver, keeping only the addresses the policy allows."""

    def __init__(self, policy: UrlPolicy, resolver: AbstractResolver | None = None):
        self.policy = policy
        self._resolver = resolver or DefaultResolver()

    async def resolve(self, host: str, port: int = 0, family: socket.AddressFamily = socket.AF_INET,
                      ) -> list[ResolveResult]:
        return self.policy.resolved(host, await self._resolver.resolve(host, port, family))

    async def close(self) -> None:
        await self._resolver.close()
