// What the error panel shows: every failure the page reports names what failed.

/** A manifest (or a document beside it) that is malformed or outside the profile. */
export class ManifestError extends Error {
  override name = "ManifestError";
}

/** A URL the policy does not let the page fetch. */
export class RefusedUrlError extends Error {
  override name = "RefusedUrlError";
}

/** A segment that is corrupt or does not match what the manifest announced. */
export class SegmentError extends Error {
  override name = "SegmentError";
}

/** What this browser cannot do (no WebCodecs AV1, no WebGL2 float render targets). */
export class UnsupportedError extends Error {
  override name = "UnsupportedError";
}

/** A request that failed (status, network). */
export class FetchError extends Error {
  override name = "FetchError";
}

export function describe(err: unknown): string {
  if (err instanceof Error) return `${err.name === "Error" ? "error" : err.name}: ${err.message}`;
  return String(err);
}
