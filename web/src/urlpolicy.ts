// Which URLs the page follows (stgs/client/urlpolicy.py's rules, as far as a page can apply them): http(s) only; the
// manifest's host and the hosts its own BaseURLs name; never a link-local literal (169.254.0.0/16, fe80::/10,
// where cloud metadata services answer); a loopback literal only when the manifest itself is on loopback. A page
// cannot see what a name resolves to, so a name pointing at a refused address is not caught here (DNS
// rebinding is the browser's and the network's to stop; docs/SECURITY.md).
import { RefusedUrlError } from "./errors";

function ipv4(host: string): number[] | null {
  const m = /^(\d{1,3})\.(\d{1,3})\.(\d{1,3})\.(\d{1,3})$/.exec(host);
  if (!m) return null;
  const parts = m.slice(1).map(Number);
  return parts.every((p) => p <= 255) ? parts : null;
}

function isLinkLocal(host: string): boolean {
  const v4 = ipv4(host);
  if (v4) return v4[0] === 169 && v4[1] === 254;
  const h = host.replace(/^\[|\]$/g, "").toLowerCase();
  if (h.startsWith("::ffff:")) return isLinkLocal(h.slice(7));
  return /^fe[89ab][0-9a-f]:/.test(h);
}

function isLoopback(host: string): boolean {
  const v4 = ipv4(host);
  if (v4) return v4[0] === 127;
  const h = host.replace(/^\[|\]$/g, "").toLowerCase();
  return h === "localhost" || h === "::1" || h.startsWith("::ffff:127.");
}

function isUnspecified(host: string): boolean {
  const h = host.replace(/^\[|\]$/g, "");
  return h === "0.0.0.0" || h === "::";
}

export class UrlPolicy {
  readonly hosts = new Set<string>();
  private readonly loopback: boolean;

  constructor(readonly manifestUrl: string) {
    const url = new URL(manifestUrl);
    this.hosts.add(url.hostname.toLowerCase());
    this.loopback = isLoopback(url.hostname);
  }

  /** Add the hosts of the manifest's own absolute BaseURLs. */
  allowHostsOf(urls: string[]): void {
    for (const u of urls) {
      try {
        const url = new URL(u);
        if (url.protocol === "http:" || url.protocol === "https:") this.hosts.add(url.hostname.toLowerCase());
      } catch {
        // a relative BaseURL names no host
      }
    }
  }

  check(raw: string): void {
    let url: URL;
    try {
      url = new URL(raw);
    } catch {
      throw new RefusedUrlError(`not a URL: ${raw.slice(0, 200)}`);
    }
    if (url.protocol !== "http:" && url.protocol !== "https:") {
      throw new RefusedUrlError(`only http and https URLs are followed, not ${url.protocol} (${raw.slice(0, 200)})`);
    }
    const host = url.hostname.toLowerCase();
    if (!this.hosts.has(host)) {
      throw new RefusedUrlError(`host ${host} is neither the manifest's nor named by its BaseURLs`);
    }
    if (isLinkLocal(host)) throw new RefusedUrlError(`${host} is a link-local address, refused`);
    if (isUnspecified(host)) throw new RefusedUrlError(`${host} is the unspecified address, refused`);
    if (isLoopback(host) && !this.loopback) {
      throw new RefusedUrlError(`${host} is a loopback address and the manifest is not on loopback, refused`);
    }
  }
}
