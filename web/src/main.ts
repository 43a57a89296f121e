// The page's entry: options from the query string (?mpd=URL&abr=&quality=&camera=&size=WxH&autoplay=&gop=
// &loop=0|1&speed=&buffer=GOPs&background=r,g,b; for tests and benchmarks timing=sync, debug=features,
// weights=uniform|texture, deform=webgpu), a deep link's moment and view from the fragment (#t=&cam=, link.ts),
// the assets the build named, then the player and its controls (a still scene: the camera's alone). Without ?mpd it
// lists the scenes of the server it came from (stgs serve's /scenes), when there is one.
import { RULES } from "./abr/index";
import { SPEEDS } from "./clock";
import { describe, UnsupportedError } from "./errors";
import { applyLink } from "./link";
import { Player, type PlayerOptions } from "./player";
import type { Assets } from "./stream/worker-pools";
import { bindControls, showError, showScene } from "./ui";

declare global {
  interface Window {
    stgsPlayer?: Player;
  }
}

async function main(): Promise<void> {
  const params = new URLSearchParams(location.search);
  const assets = JSON.parse(document.querySelector<HTMLMetaElement>('meta[name="stgs-assets"]')!.content) as Assets;
  const mpd = params.get("mpd");
  if (!mpd) return listScenes();
  const abr = params.get("abr") ?? "dynamic";
  if (!(abr in RULES)) throw new Error(`abr=${abr} is not a rule; known: ${Object.keys(RULES).join(", ")}`);
  const size = params.get("size");
  const sizeMatch = size ? /^(\d{1,5})x(\d{1,5})$/.exec(size) : null;
  if (size && !sizeMatch) throw new Error(`size=${size} is not WIDTHxHEIGHT`);
  const bg = (params.get("background") ?? "0,0,0").split(",").map(Number);
  const loop = params.get("loop");
  if (loop !== null && loop !== "0" && loop !== "1") throw new Error(`loop=${loop} is not 0 or 1`);
  const speed = Number(params.get("speed") ?? 1);
  if (!(SPEEDS as readonly number[]).includes(speed))
    throw new Error(`speed=${params.get("speed")} is not one of ${SPEEDS}`);
  const options: PlayerOptions = {
    abr,
    rung: null,
    bufferGops: Number(params.get("buffer") ?? 3) || 3,
    background: [bg[0] || 0, bg[1] || 0, bg[2] || 0],
    size: sizeMatch ? [Number(sizeMatch[1]), Number(sizeMatch[2])] : null,
    syncTiming: params.get("timing") === "sync",
    digests: params.get("debug") === "features",
    weights: null,
    webgpu: params.get("deform") === "webgpu",
    loop: loop === null ? null : loop === "1",
  };
  const weights = params.get("weights");
  if (weights !== null && weights !== "uniform" && weights !== "texture")
    throw new Error(`weights=${weights} is not uniform or texture`);
  options.weights = weights;
  const player = new Player(document.getElementById("view") as HTMLCanvasElement, assets, options);
  window.stgsPlayer = player;
  player.onError = showError;
  player.onScene = (face) => void showScene(face, player.manifest.policy);
  const status = document.getElementById("status")!;
  status.textContent = "loading…";
  const quality = params.get("quality");
  if (params.get("autoplay") === "0") player.paused = true;
  await player.load(mpd);
  if (!player.still) await checkDecoder(player);
  if (quality !== null && quality !== "auto" && !player.still) {
    const rung = player.manifest.rungs.findIndex((r) => r.id === quality);
    if (rung < 0)
      throw new Error(
        `quality=${quality} is not a rung; the scene has ${player.manifest.rungs.map((r) => r.id).join(", ")}`,
      );
    player.options.rung = rung;
    player.setRung(rung);
  }
  const camera = params.get("camera");
  if (camera !== null) {
    const index = player.cameras.findIndex((c) => c.name === camera);
    if (index < 0) throw new Error(`camera=${camera} is not a camera of this scene`);
    player.snapTo(index);
  }
  const gop = Number(params.get("gop") ?? 0);
  if (gop > 0) player.seek(gop);
  if (speed !== 1) player.setSpeed(speed);
  const followLink = () => {
    for (const warning of applyLink(player, location.hash)) console.warn(`deep link ignored: ${warning}`);
  };
  followLink();
  window.addEventListener("hashchange", followLink);
  bindControls(player);
  status.textContent = "";
  document.getElementById("view")!.focus();
}

/** The feature video's codec is one this browser's WebCodecs decodes. */
async function checkDecoder(player: Player): Promise<void> {
  const codec = player.manifest.rungs[0]!.codecs;
  const side = 4 * player.manifest.shape.side;
  const { supported } = await VideoDecoder.isConfigSupported({ codec, codedWidth: side, codedHeight: side });
  if (!supported)
    throw new UnsupportedError(
      `this browser's WebCodecs cannot decode ${codec} (AV1 10-bit), which the feature video needs`,
    );
}

async function listScenes(): Promise<void> {
  const status = document.getElementById("status")!;
  try {
    const response = await fetch(new URL("../scenes", location.href), { credentials: "omit" });
    const { scenes } = (await response.json()) as { scenes: { name: string; manifest: string; error?: string }[] };
    const list = document.createElement("ul");
    list.setAttribute("aria-label", "Scenes");
    for (const s of scenes) {
      const item = document.createElement("li");
      const link = document.createElement("a");
      link.href = `?mpd=${encodeURIComponent(new URL(s.manifest, location.href).href)}`;
      link.textContent = s.name === "." ? "scene" : s.name;
      item.append(link, s.error ? ` (${s.error})` : "");
      list.append(item);
    }
    document.getElementById("error")!.replaceChildren(list);
    document.getElementById("error")!.hidden = false;
  } catch {
    showError("no manifest: open this page with ?mpd=URL of a scene's manifest.mpd");
  }
  status.textContent = "";
}

main().catch((err) => showError(describe(err)));
