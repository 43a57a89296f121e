// Requests: every URL checked by the policy first (and the final URL again after redirects, before a byte of
// the body is read); the length checked against the cap before allocating; bodies read as a stream, so a
// segment can be fed to its decoder as it arrives and its throughput measured on the body alone.
import { FetchError, RefusedUrlError } from "../errors";
import type { UrlPolicy } from "../urlpolicy";
import type { ThroughputSample } from "../abr/state";

export interface Fetched {
  data: ArrayBuffer;
  sample: ThroughputSample;
}

export async function fetchStream(
  url: string,
  policy: UrlPolicy,
  maxBytes: number,
  what: string,
  signal: AbortSignal | null,
  onChunk?: (chunk: Uint8Array) => void,
): Promise<Fetched> {
  policy.check(url);
  const start = performance.now();
  let response: Response;
  try {
    response = await fetch(url, { signal, credentials: "omit", mode: "cors", redirect: "follow" });
  } catch (err) {
    if (signal?.aborted) throw err;
    throw new FetchError(`${what}: ${url} is unreachable (${err instanceof Error ? err.message : err})`);
  }
  const ttfb = (performance.now() - start) / 1e3;
  if (response.redirected) {
    try {
      policy.check(response.url);
    } catch (err) {
      void response.body?.cancel();
      throw new RefusedUrlError(`${what} redirected: ${(err as Error).message}`);
    }
  }
  if (!response.ok) {
    void response.body?.cancel();
    throw new FetchError(`${what}: ${url} answered HTTP ${response.status}`);
  }
  const length = Number(response.headers.get("Content-Length") ?? NaN);
  if (length > maxBytes) {
    void response.body?.cancel();
    throw new FetchError(`${what}: ${url} is ${length} bytes, over the ${maxBytes}-byte limit`);
  }
  const body = new Uint8Array(Number.isFinite(length) ? length : Math.min(maxBytes, 1 << 20));
  let data = body;
  let received = 0;
  const reader = response.body!.getReader();
  for (;;) {
    const { done, value } = await reader.read();
    if (done) break;
    if (received + value.byteLength > maxBytes) {
      void reader.cancel();
      throw new FetchError(`${what}: ${url} sent more than the ${maxBytes}-byte limit`);
    }
    if (received + value.byteLength > data.length) {
      const grown = new Uint8Array(Math.min(maxBytes, Math.max(2 * data.length, received + value.byteLength)));
      grown.set(data.subarray(0, received));
      data = grown;
    }
    data.set(value, received);
    received += value.byteLength;
    onChunk?.(value);
  }
  if (Number.isFinite(length) && received !== length)
    throw new FetchError(`${what}: ${url} ended after ${received} of ${length} bytes`);
  const seconds = (performance.now() - start) / 1e3;
  return { data: data.buffer.slice(0, received) as ArrayBuffer, sample: { bytes: received, seconds, ttfb } };
}

export async function fetchJson(url: string, policy: UrlPolicy, maxBytes: number, what: string): Promise<unknown> {
  const { data } = await fetchStream(url, policy, maxBytes, what, null);
  try {
    return JSON.parse(new TextDecoder("utf-8", { fatal: true }).decode(data));
  } catch (err) {
    throw new FetchError(`${what} is not JSON (${err instanceof Error ? err.message : err})`);
  }
}
