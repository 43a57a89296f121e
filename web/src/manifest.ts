// The MPD as the page sees it (stgs/client/manifest.py's checks, manifests/PROFILE.md): one static Period; the
// keyframe set, the optional static-layer set and the AV1 10-bit feature set found by their scheme URIs (a still
// scene: the static-layer set alone);
// the scene's sizes read from the descriptors and checked against the caps before anything is fetched;
// SegmentTemplates resolved against the MPD's URL and its BaseURLs, every URL checked by the URL policy.
import { LOSSLESS, parseQuant, type KeyframeQuant } from "./container";
import { ManifestError, UnsupportedError } from "./errors";
import * as L from "./limits";
import { UrlPolicy } from "./urlpolicy";

const NS = "urn:mpeg:dash:schema:mpd:2011";
export const PROFILE = "urn:streamstgs:profile:2026";
export const KEYFRAME_SCHEME = "urn:streamstgs:keyframe:2026";
export const STATIC_SCHEME = "urn:streamstgs:static:2026";
export const FEATURE_SCHEME = "urn:streamstgs:features:2026";
export const QUALITY_SCHEME = "urn:streamstgs:quality:2026";
export const KEYFRAME_QUANT_SCHEME = "urn:streamstgs:keyframe-quant:2026";
/** The lossless keyframe Representation's id (stgs/tree.py KEYFRAME_REP): its bytes are stats.json's keyframe_bytes. */
export const KEYFRAME_REP = "keyframes";
export const AV1_BITS = 10;
export const FEATURE_TILES = 4;

export interface SceneShape {
  capacity: number;
  side: number;
  gopSize: number;
  window: number;
  peFreqs: number;
  /** E = G + W - 1 feature frames per GOP. */
  numFeatures: number;
}

export interface Rung {
  id: string;
  bandwidth: number;
  codecs: string;
  /** Mean rendered PSNR (dB) against the uncompressed model, from its quality descriptor; null in trees without one. */
  renderPsnr: number | null;
  /** Mean PSNR (dB) against the capture as the packager estimated it; null where the descriptor does not give it. */
  truthPsnr: number | null;
  /** The keyframe Representation it plays with (its @associationId). */
  keyframeRep: string;
  keyframeBandwidth: number;
}

/** One keyframe Representation: the lossless one, or a lossy keyframe rung. */
export interface KeyframeRep {
  id: string;
  bandwidth: number;
  quant: KeyframeQuant;
}

export interface StaticLayerInfo {
  capacity: number;
  side: number;
  shDegree: number;
  url: string;
  bandwidth: number;
}

export interface Manifest {
  url: string;
  /** A still scene (manifests/PROFILE.md, "A still scene"): the static layer alone, no GOP, no clock. Its `gops` is 0,
   * `rungs` empty, `shape` all zeros, and the segment URL functions throw. */
  still: boolean;
  durationS: number;
  gops: number;
  gopSeconds: number;
  fps: number;
  shape: SceneShape;
  staticLayer: StaticLayerInfo | null;
  keyframeReps: Map<string, KeyframeRep>;
  /** Feature rungs by rising total bandwidth (features and their keyframes; stgs/client/manifest.py's order). */
  rungs: Rung[];
  /** Codecs of the HEVC set when the tree also has one (the page cannot decode it). */
  otherCodecs: string[];
  keyframeUrl(k: number, rep: string): string;
  /** Per rung, the bit/s an ABR rule weighs: its features plus its keyframes beyond the ladder's cheapest. */
  abrBandwidths(): number[];
  initUrl(rung: number): string;
  mediaUrl(rung: number, k: number): string;
  /** Largest byte size a segment of this bandwidth may have (the packager's @bandwidth covers the largest). */
  maxSegmentBytes(bandwidth: number): number;
  statsUrl: string;
  camerasUrl: string;
  /** scene.json beside the MPD: title, description and poster (stgs pack; absent from older trees). */
  sceneUrl: string;
  policy: UrlPolicy;
}

/** A segment's size cap: what its @bandwidth delivers over `seconds`, with slack (stgs/client/manifest.py
 * segment_cap). */
export function segmentCap(bandwidth: number, seconds: number): number {
  return Math.min(L.MAX_SEGMENT_BYTES, Math.ceil((bandwidth / 8) * seconds * L.SEGMENT_SLACK) + 4096);
}

function fail(message: string): never {
  throw new ManifestError(message);
}

export function parseDuration(text: string | null, what: string): number {
  const m = text
    ? /^P(?:(\d+(?:\.\d+)?)D)?(?:T(?:(\d+(?:\.\d+)?)H)?(?:(\d+(?:\.\d+)?)M)?(?:(\d+(?:\.\d+)?)S)?)?$/.exec(text.trim())
    : null;
  if (!m || text === "P" || text === "PT") fail(`${what} is not an ISO 8601 duration: ${JSON.stringify(text)}`);
  const [d = 0, h = 0, min = 0, s = 0] = m.slice(1).map((v) => (v ? Number(v) : 0));
  const seconds = d * 86400 + h * 3600 + min * 60 + s;
  if (!Number.isFinite(seconds) || seconds <= 0 || seconds > L.MAX_DURATION_S) fail(`${what} ${text} is out of range`);
  return seconds;
}

/** "k=v;k=v" of a SupplementalProperty's @value. */
export function descriptorFields(value: string, what: string): Map<string, string> {
  const fields = new Map<string, string>();
  for (const part of value.split(";")) {
    const eq = part.indexOf("=");
    if (eq <= 0) fail(`${what} descriptor ${JSON.stringify(value.slice(0, 100))} is not k=v;k=v`);
    fields.set(part.slice(0, eq).trim(), part.slice(eq + 1).trim());
  }
  return fields;
}

function intField(fields: Map<string, string>, key: string, lo: number, hi: number, what: string): number {
  const raw = fields.get(key);
  if (raw === undefined) fail(`${what} descriptor lacks ${key}`);
  if (!/^\d{1,10}$/.test(raw)) fail(`${what} descriptor ${key}=${raw} is not an integer`);
  const v = Number(raw);
  if (v < lo || v > hi) fail(`${what} descriptor ${key}=${v} is outside ${lo}..${hi}`);
  return v;
}

function intAttr(el: Element, name: string, lo: number, hi: number, fallback?: number): number {
  const raw = el.getAttribute(name);
  if (raw === null) {
    if (fallback !== undefined) return fallback;
    fail(`${el.localName} lacks @${name}`);
  }
  if (!/^\d{1,15}$/.test(raw)) fail(`${el.localName} @${name}=${raw.slice(0, 40)} is not an integer`);
  const v = Number(raw);
  if (v < lo || v > hi) fail(`${el.localName} @${name}=${v} is outside ${lo}..${hi}`);
  return v;
}

export function expandTemplate(template: string, repId: string, num?: number): string {
  return template.replace(/\$([A-Za-z]*)(%[^$]*)?\$/g, (_, name: string, fmt: string | undefined) => {
    if (name === "") return "$";
    if (name === "RepresentationID") return repId;
    if (name === "Number") {
      if (num === undefined) fail(`template ${template} needs $Number$`);
      if (!fmt) return String(num);
      const w = /^%0(\d{1,3})d$/.exec(fmt);
      if (!w) fail(`unsupported format tag ${fmt} in ${template}`);
      if (Number(w[1]) > L.MAX_TEMPLATE_NUMBER_WIDTH) fail(`$Number$ width ${w[1]} is over the limit`);
      return String(num).padStart(Number(w[1]), "0");
    }
    fail(`unsupported identifier $${name}$ in ${template}`);
  });
}

/** A feature Representation's quality descriptor (manifests/PROFILE.md): render_psnr (and truth_psnr, where given) in
 * 0..99 dB; both null without one. */
function quality(rep: Element, id: string): { renderPsnr: number | null; truthPsnr: number | null } {
  const prop = children(rep, "SupplementalProperty").find((p) => p.getAttribute("schemeIdUri") === QUALITY_SCHEME);
  if (!prop) return { renderPsnr: null, truthPsnr: null };
  const fields = descriptorFields(prop.getAttribute("value") ?? "", "quality");
  const db = (key: string, optional: boolean): number | null => {
    const raw = fields.get(key);
    if (raw === undefined && optional) return null;
    if (raw === undefined || !/^\d{1,2}(\.\d{1,6})?$/.test(raw)) {
      fail(
        `quality descriptor of Representation ${id}: ${key}=${String(raw).slice(0, 40)} is not a number in 0..99 dB`,
      );
    }
    return Number(raw);
  };
  return { renderPsnr: db("render_psnr", false), truthPsnr: db("truth_psnr", true) };
}

function children(el: Element, name: string): Element[] {
  return Array.from(el.children).filter((c) => c.namespaceURI === NS && c.localName === name);
}

function scheme(set: Element): Element | null {
  return (
    children(set, "SupplementalProperty").find((p) => p.getAttribute("schemeIdUri")?.startsWith("urn:streamstgs:")) ??
    null
  );
}

interface Template {
  media: string;
  init: string | null;
  seconds: number;
  start: number;
}

function template(set: Element): Template {
  const [t] = children(set, "SegmentTemplate");
  if (!t) fail(`AdaptationSet ${set.getAttribute("id")} has no SegmentTemplate`);
  const timescale = intAttr(t, "timescale", 1, 1e12, 1);
  const duration = intAttr(t, "duration", 1, 1e15);
  const media = t.getAttribute("media") ?? fail("SegmentTemplate lacks @media");
  return {
    media,
    init: t.getAttribute("initialization"),
    seconds: duration / timescale,
    start: intAttr(t, "startNumber", 0, 1e9, 1),
  };
}

function baseOf(el: Element, base: string, policy: UrlPolicy): string {
  const [b] = children(el, "BaseURL");
  if (!b?.textContent) return base;
  const resolved = new URL(b.textContent.trim(), base).href;
  policy.allowHostsOf([resolved]);
  return resolved;
}

/** Parse and check an MPD fetched from `url`. */
export function parseManifest(text: string, url: string): Manifest {
  if (text.length > L.MAX_MPD_BYTES) fail(`the manifest is over ${L.MAX_MPD_BYTES} bytes`);
  if (/<!DOCTYPE|<!ENTITY/i.test(text)) fail("the manifest has a DOCTYPE or an entity declaration (refused)");
  const doc = new DOMParser().parseFromString(text, "application/xml");
  const error = doc.getElementsByTagName("parsererror")[0];
  if (error) fail(`the manifest is not XML (${(error.textContent ?? "").trim().split("\n")[0]!.slice(0, 160)})`);
  const mpd = doc.documentElement;
  if (mpd.namespaceURI !== NS || mpd.localName !== "MPD") fail("the document is not an MPEG-DASH MPD");
  if (mpd.getAttribute("type") !== null && mpd.getAttribute("type") !== "static") fail("only static MPDs are played");
  if (
    !(mpd.getAttribute("profiles") ?? "")
      .split(",")
      .map((p) => p.trim())
      .includes(PROFILE)
  ) {
    fail(`the MPD does not declare the StreamSTGS profile (${PROFILE})`);
  }
  const periods = children(mpd, "Period");
  if (periods.length !== 1) fail(`a StreamSTGS MPD has exactly one Period, this one has ${periods.length}`);
  const policy = new UrlPolicy(url);
  const base = baseOf(periods[0]!, baseOf(mpd, url, policy), policy);
  const sets = children(periods[0]!, "AdaptationSet");
  if (sets.length > L.MAX_ADAPTATION_SETS)
    fail(`the Period has ${sets.length} AdaptationSets, over ${L.MAX_ADAPTATION_SETS}`);
  const bySchema = (s: string) => sets.filter((a) => scheme(a)?.getAttribute("schemeIdUri") === s);
  const durationS = parseDuration(mpd.getAttribute("mediaPresentationDuration"), "@mediaPresentationDuration");

  let staticLayer: StaticLayerInfo | null = null;
  const staticSets = bySchema(STATIC_SCHEME);
  if (staticSets.length > 1) fail("the MPD has more than one static-layer AdaptationSet");
  if (staticSets.length === 1) {
    const sset = staticSets[0]!;
    const sf = descriptorFields(scheme(sset)!.getAttribute("value") ?? "", "static-layer");
    const scap = intField(sf, "capacity", 1, L.MAX_CAPACITY, "static-layer");
    const sside = intField(sf, "grid_side", 1, 2048, "static-layer");
    if (sside * sside !== scap) fail(`static-layer grid_side ${sside} does not square to capacity ${scap}`);
    const shDegree = intField(sf, "sh_degree", 0, 1, "static-layer");
    const reps = children(sset, "Representation");
    if (reps.length !== 1) fail("the static-layer AdaptationSet must have exactly one Representation");
    const st = template(sset);
    const surl = new URL(
      expandTemplate(st.media, reps[0]!.getAttribute("id") ?? "", st.start),
      baseOf(sset, base, policy),
    ).href;
    staticLayer = {
      capacity: scap,
      side: sside,
      shDegree,
      url: surl,
      bandwidth: intAttr(reps[0]!, "bandwidth", 1, 1e12),
    };
  }

  const sceneUrls = {
    statsUrl: new URL("stats.json", url).href,
    camerasUrl: new URL("cameras.json", url).href,
    sceneUrl: new URL("scene.json", url).href,
  };
  if (staticLayer && bySchema(KEYFRAME_SCHEME).length === 0) {
    if (bySchema(FEATURE_SCHEME).length) fail("a still scene (no keyframe AdaptationSet) has no feature set either");
    policy.check(staticLayer.url);
    return stillManifest(url, durationS, staticLayer, sceneUrls, policy);
  }

  const keyframeSets = bySchema(KEYFRAME_SCHEME);
  if (keyframeSets.length !== 1) fail(`the MPD needs exactly one keyframe AdaptationSet (${KEYFRAME_SCHEME})`);
  const kset = keyframeSets[0]!;
  const kf = descriptorFields(scheme(kset)!.getAttribute("value") ?? "", "keyframe");
  if (kf.get("version") !== "1") fail(`keyframe descriptor version ${kf.get("version")} is not 1`);
  const capacity = intField(kf, "capacity", 1, L.MAX_CAPACITY, "keyframe");
  const side = intField(kf, "grid_side", 1, 2048, "keyframe");
  if (side * side !== capacity) fail(`keyframe descriptor grid_side ${side} does not square to capacity ${capacity}`);
  const gopSize = intField(kf, "gop_size", 1, L.MAX_GOP_SIZE, "keyframe");
  const window = intField(kf, "window", 1, L.MAX_WINDOW, "keyframe");
  const peFreqs = intField(kf, "pe_freqs", 0, L.MAX_PE_FREQS, "keyframe");
  const fps = Number(kf.get("fps"));
  if (!(fps >= L.MIN_FPS && fps <= L.MAX_FPS))
    fail(`keyframe descriptor fps=${kf.get("fps")} is outside ${L.MIN_FPS}..${L.MAX_FPS}`);
  const shape: SceneShape = { capacity, side, gopSize, window, peFreqs, numFeatures: gopSize + window - 1 };
  const kt = template(kset);
  const kbase = baseOf(kset, base, policy);
  const keyframeReps = new Map<string, KeyframeRep>();
  for (const r of children(kset, "Representation")) {
    const id = r.getAttribute("id") ?? fail("a keyframe Representation lacks @id");
    if (!/^[A-Za-z0-9_.-]{1,64}$/.test(id))
      fail(`keyframe Representation id ${JSON.stringify(id.slice(0, 70))} is not a plain name`);
    if (keyframeReps.has(id)) fail(`two keyframe Representations share the id ${id}`);
    const prop = children(r, "SupplementalProperty").find(
      (p) => p.getAttribute("schemeIdUri") === KEYFRAME_QUANT_SCHEME,
    );
    let quant = LOSSLESS;
    if (prop) {
      try {
        quant = parseQuant(prop.getAttribute("value") ?? "");
      } catch (e) {
        fail(`keyframe Representation ${id}: ${e instanceof Error ? e.message : e}`);
      }
    }
    keyframeReps.set(id, { id, bandwidth: intAttr(r, "bandwidth", 1, 1e12), quant });
  }
  if (keyframeReps.size === 0) fail("the keyframe AdaptationSet has no Representation");
  const gopSeconds = kt.seconds;
  if (Math.abs(gopSeconds * fps - gopSize) > 1e-3 * gopSize)
    fail(`a GOP lasts ${gopSeconds} s, not ${gopSize} frames at ${fps} fps`);
  const gops = Math.round(durationS / gopSeconds);
  if (gops < 1 || gops > L.MAX_GOPS) fail(`the presentation has ${gops} GOPs, outside 1..${L.MAX_GOPS}`);

  const featureSets = bySchema(FEATURE_SCHEME);
  if (featureSets.length === 0) fail(`the MPD has no feature-video AdaptationSet (${FEATURE_SCHEME})`);
  const av1 = featureSets.filter((a) => {
    const reps = children(a, "Representation");
    return (
      reps.length > 0 &&
      reps.every((r) => (r.getAttribute("codecs") ?? a.getAttribute("codecs") ?? "").startsWith("av01."))
    );
  });
  const otherCodecs = featureSets
    .filter((a) => !av1.includes(a))
    .flatMap((a) => children(a, "Representation").map((r) => r.getAttribute("codecs") ?? "?"));
  if (av1.length === 0) {
    throw new UnsupportedError(
      `this tree has no AV1 feature set, only ${[...new Set(otherCodecs)].join(", ")}, which ` +
        "browsers cannot decode; pack it with --codecs hevc,av1",
    );
  }
  if (av1.length > 1) fail("the MPD has two AV1 feature sets");
  const fset = av1[0]!;
  const ff = descriptorFields(scheme(fset)!.getAttribute("value") ?? "", "feature");
  if (ff.get("tiles") !== "4x4" || ff.get("channels") !== "16")
    fail("the feature descriptor is not tiles=4x4;channels=16");
  if (ff.get("bits") !== String(AV1_BITS)) fail(`the AV1 feature set carries bits=${ff.get("bits")}, not ${AV1_BITS}`);
  const ft = template(fset);
  if (Math.abs(ft.seconds - gopSeconds) > 1e-9 * gopSeconds || ft.start !== kt.start)
    fail("the feature and keyframe segment templates differ in duration or start");
  if (!ft.init) fail("the feature SegmentTemplate lacks @initialization");
  const reps = children(fset, "Representation");
  if (reps.length > L.MAX_REPRESENTATIONS)
    fail(`the AV1 set has ${reps.length} Representations, over ${L.MAX_REPRESENTATIONS}`);
  const frameSide = FEATURE_TILES * side;
  const rungs: Rung[] = reps
    .map((r) => {
      const id = r.getAttribute("id") ?? fail("a feature Representation lacks @id");
      if (!/^[A-Za-z0-9_.-]{1,64}$/.test(id))
        fail(`feature Representation id ${JSON.stringify(id.slice(0, 70))} is not a plain name`);
      const w = intAttr(r, "width", 1, L.MAX_IMAGE_SIDE, intAttr(fset, "width", 1, L.MAX_IMAGE_SIDE, frameSide));
      const h = intAttr(r, "height", 1, L.MAX_IMAGE_SIDE, intAttr(fset, "height", 1, L.MAX_IMAGE_SIDE, frameSide));
      if (w !== frameSide || h !== frameSide)
        fail(`Representation ${id} is ${w}x${h}, not the ${frameSide}x${frameSide} of grid_side ${side}`);
      const named = (r.getAttribute("associationId") ?? "").split(/\s+/).filter((a) => keyframeReps.has(a));
      if (named.length !== 1) {
        fail(
          `feature Representation ${id} must name one keyframe Representation in @associationId ` +
            `(of ${[...keyframeReps.keys()].join(", ")}), it names ${r.getAttribute("associationId") || "none"}`,
        );
      }
      const kf = keyframeReps.get(named[0]!)!;
      return {
        id,
        bandwidth: intAttr(r, "bandwidth", 1, 1e12),
        codecs: r.getAttribute("codecs") ?? fset.getAttribute("codecs") ?? "",
        ...quality(r, id),
        keyframeRep: kf.id,
        keyframeBandwidth: kf.bandwidth,
      };
    })
    .sort(
      (a, b) =>
        a.bandwidth + a.keyframeBandwidth - (b.bandwidth + b.keyframeBandwidth) ||
        (a.id < b.id ? -1 : a.id > b.id ? 1 : 0),
    );
  if (new Set(rungs.map((r) => r.id)).size !== rungs.length) fail("two feature Representations share an id");
  const fbase = baseOf(fset, base, policy);
  const check = (u: string) => {
    policy.check(u);
    return u;
  };
  const manifest: Manifest = {
    url,
    still: false,
    durationS,
    gops,
    gopSeconds,
    fps,
    shape,
    staticLayer,
    rungs,
    otherCodecs,
    keyframeReps,
    keyframeUrl: (k, rep) => {
      if (!keyframeReps.has(rep)) throw new ManifestError(`no keyframe Representation ${JSON.stringify(rep)}`);
      return check(new URL(expandTemplate(kt.media, rep, kt.start + k), kbase).href);
    },
    abrBandwidths: () => {
      const base = Math.min(...rungs.map((r) => r.keyframeBandwidth));
      return rungs.map((r) => r.bandwidth + r.keyframeBandwidth - base);
    },
    initUrl: (i) => check(new URL(expandTemplate(ft.init!, rungs[i]!.id), fbase).href),
    mediaUrl: (i, k) => check(new URL(expandTemplate(ft.media, rungs[i]!.id, ft.start + k), fbase).href),
    maxSegmentBytes: (bandwidth) => segmentCap(bandwidth, gopSeconds),
    ...sceneUrls,
    policy,
  };
  if (staticLayer) policy.check(staticLayer.url);
  for (const rep of keyframeReps.keys()) manifest.keyframeUrl(0, rep);
  manifest.mediaUrl(0, 0);
  return manifest;
}

/** A still scene's manifest: the static layer alone (no GOP, rung or segment template besides its one segment). */
function stillManifest(
  url: string,
  durationS: number,
  staticLayer: StaticLayerInfo,
  urls: { statsUrl: string; camerasUrl: string; sceneUrl: string },
  policy: UrlPolicy,
): Manifest {
  const none = (): never => fail("a still scene has no GOP segments");
  return {
    url,
    still: true,
    durationS,
    gops: 0,
    gopSeconds: durationS,
    fps: 1,
    shape: { capacity: 0, side: 0, gopSize: 0, window: 0, peFreqs: 0, numFeatures: 0 },
    staticLayer,
    keyframeReps: new Map(),
    rungs: [],
    otherCodecs: [],
    keyframeUrl: none,
    abrBandwidths: () => [],
    initUrl: none,
    mediaUrl: none,
    maxSegmentBytes: (bandwidth) => segmentCap(bandwidth, durationS),
    ...urls,
    policy,
  };
}
