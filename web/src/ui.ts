// The viewer's controls: orbit and fly with mouse, touch and keys; play/pause, seek bar, loop, speed, quality
// menu (none of these five for a still scene), scene cameras, stats overlay, link, screenshot, full screen; the
// scene's title and poster; and the error panel. Every control is a native, focusable element.
import { SPEEDS } from "./clock";
import * as L from "./limits";
import { linkFragment } from "./link";
import type { Rung } from "./manifest";
import type { Player } from "./player";
import type { SceneFace } from "./scene";
import { fetchStream } from "./stream/fetch";
import type { UrlPolicy } from "./urlpolicy";

const $ = <T extends HTMLElement>(id: string) => document.getElementById(id) as T;

export function showError(message: string): void {
  const panel = $("error");
  panel.textContent = message;
  panel.hidden = false;
  console.error(message); // for the developer tools, and for a driving script's log
}

/** The scene's title over the view (as text) and its poster until the first frame is shown. */
export async function showScene(face: SceneFace | null, policy: UrlPolicy): Promise<void> {
  if (!face) return;
  const title = $("title");
  title.textContent = face.title;
  title.title = face.description;
  title.hidden = false;
  document.title = `${face.title} · streamstgs`;
  if (!face.posterUrl) return;
  try {
    const { data } = await fetchStream(face.posterUrl, policy, L.MAX_POSTER_BYTES, "poster", null);
    const poster = $<HTMLImageElement>("poster");
    if (poster.dataset.done) return; // the first frame came first
    poster.src = URL.createObjectURL(new Blob([data as BlobPart], { type: "image/webp" }));
    poster.hidden = false;
  } catch (err) {
    console.warn(`the poster could not be shown: ${err instanceof Error ? err.message : err}`);
  }
}

/** Save the canvas as a PNG (the canvas's own resolution) named after the scene and the moment. */
function saveScreenshot(player: Player): void {
  const canvas = $<HTMLCanvasElement>("view");
  canvas.toBlob((blob) => {
    if (!blob) return;
    const a = document.createElement("a");
    a.href = URL.createObjectURL(blob);
    const name = (player.scene?.title ?? "scene").replace(/[^\w-]+/g, "_").slice(0, 60) || "scene";
    a.download = `${name}-t${player.shownTimeS().toFixed(2)}s.png`;
    a.click();
    setTimeout(() => URL.revokeObjectURL(a.href), 10_000);
  }, "image/png");
}

export function bindControls(player: Player): void {
  const canvas = $<HTMLCanvasElement>("view");
  const play = $<HTMLButtonElement>("play");
  const seek = $<HTMLInputElement>("seek");
  const time = $<HTMLOutputElement>("time");
  const quality = $<HTMLSelectElement>("quality");
  const camera = $<HTMLSelectElement>("camera");
  const statsToggle = $<HTMLButtonElement>("stats-toggle");
  const stats = $<HTMLPreElement>("stats");
  const loop = $<HTMLButtonElement>("loop");
  const speed = $<HTMLSelectElement>("speed");
  const poster = $<HTMLImageElement>("poster");
  const status = $("status");
  const m = player.manifest;
  if (player.still) {
    // a still has nothing to play: the playback controls go, the camera's stay
    for (const el of [play, seek, loop, speed.parentElement!, quality.parentElement!]) el.hidden = true;
    $("controls").setAttribute("aria-label", "View controls");
  }

  for (const s of SPEEDS) speed.add(new Option(`${s}×`, String(s)));
  speed.value = String(player.speed);
  const showLoop = () => loop.setAttribute("aria-pressed", String(player.loop));
  showLoop();

  seek.max = String(m.gops - 1);
  m.rungs.forEach((r, i) => {
    quality.add(new Option(rungLabel(r), String(i)));
  });
  if (player.options.rung !== null) quality.value = String(player.options.rung);
  player.cameras.forEach((c, i) => {
    camera.add(new Option(c.name, String(i)));
  });
  const showCamera = () => {
    const posed = player.camera.pose ? player.cameras.indexOf(player.camera.pose) : -1;
    camera.value = posed >= 0 ? String(posed) : "";
  };
  showCamera();

  const showPlay = () => {
    play.textContent = player.paused ? "Play" : "Pause";
    play.setAttribute("aria-label", player.paused ? "Play" : "Pause");
  };
  showPlay();
  const togglePause = () => {
    player.togglePause();
    showPlay();
  };
  const seekTo = (k: number) => {
    player.seek(k);
    seek.value = String(k);
  };
  const toggleLoop = () => {
    player.loop = !player.loop;
    showLoop();
  };
  const copyLink = async () => {
    const url = new URL(location.href);
    url.hash = linkFragment(player);
    history.replaceState(null, "", url);
    try {
      await navigator.clipboard.writeText(url.href);
      status.textContent = "link copied";
    } catch {
      status.textContent = `link: ${url.href}`; // no clipboard (an insecure origin, or refused): shown instead
    }
  };
  const toggleStats = () => {
    stats.hidden = !stats.hidden;
    statsToggle.setAttribute("aria-pressed", String(!stats.hidden));
  };
  const fullscreen = () => {
    if (document.fullscreenElement) void document.exitFullscreen();
    else void $("player").requestFullscreen?.();
  };
  const snap = (i: number) => {
    if (i >= player.cameras.length) return;
    player.snapTo(i);
    camera.value = String(i);
  };
  const moved = () => {
    camera.value = "";
    player.invalidate();
  };

  play.onclick = togglePause;
  seek.onchange = () => seekTo(Number(seek.value));
  quality.onchange = () => player.setRung(quality.value === "auto" ? null : Number(quality.value));
  camera.onchange = () => (camera.value === "" ? moved() : snap(Number(camera.value)));
  statsToggle.onclick = toggleStats;
  loop.onclick = toggleLoop;
  speed.onchange = () => player.setSpeed(Number(speed.value));
  $<HTMLButtonElement>("link").onclick = () => void copyLink();
  $<HTMLButtonElement>("screenshot").onclick = () => saveScreenshot(player);
  $<HTMLButtonElement>("fullscreen").onclick = fullscreen;

  type Point = { x: number; y: number };
  const pointers = new Map<number, Point>();
  canvas.addEventListener("pointerdown", (e) => {
    canvas.setPointerCapture(e.pointerId);
    pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
  });
  const release = (e: PointerEvent) => pointers.delete(e.pointerId);
  canvas.addEventListener("pointerup", release);
  canvas.addEventListener("pointercancel", release);
  canvas.addEventListener("pointermove", (e) => {
    const last = pointers.get(e.pointerId);
    if (!last) return;
    const dx = e.clientX - last.x;
    const dy = e.clientY - last.y;
    if (pointers.size === 2) {
      const [a, b] = [...pointers.values()] as [Point, Point];
      const before = Math.hypot(a.x - b.x, a.y - b.y);
      pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
      const [c, d] = [...pointers.values()] as [Point, Point];
      player.camera.zoom(before / Math.max(1, Math.hypot(c.x - d.x, c.y - d.y)));
    } else if (e.shiftKey || e.buttons === 2 || e.buttons === 4) {
      pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
      player.camera.fly(0, -dx / 20, dy / 20);
    } else {
      pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
      player.camera.orbit(-dx * 0.005, dy * 0.005);
    }
    moved();
  });
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener(
    "wheel",
    (e) => {
      e.preventDefault();
      player.camera.zoom(Math.exp(e.deltaY * 0.001));
      moved();
    },
    { passive: false },
  );

  const flyKeys: Record<string, [number, number, number]> = {
    w: [1, 0, 0],
    s: [-1, 0, 0],
    a: [0, -1, 0],
    d: [0, 1, 0],
    q: [0, 0, -1],
    e: [0, 0, 1],
  };
  document.addEventListener("keydown", (e) => {
    const target = e.target as HTMLElement;
    if (e.ctrlKey || e.metaKey || e.altKey || ["INPUT", "SELECT", "TEXTAREA"].includes(target.tagName)) return;
    const key = e.key.toLowerCase();
    const G = m.shape.gopSize;
    const gop = Math.floor(Math.max(0, player.current) / G);
    if (key === " " && target.tagName !== "BUTTON") togglePause();
    else if (key === ",") seekTo(Math.max(0, gop - 1));
    else if (key === ".") seekTo(Math.min(m.gops - 1, gop + 1));
    else if (key === "arrowleft") player.camera.orbit(0.05, 0);
    else if (key === "arrowright") player.camera.orbit(-0.05, 0);
    else if (key === "arrowup") player.camera.orbit(0, 0.05);
    else if (key === "arrowdown") player.camera.orbit(0, -0.05);
    else if (key === "+" || key === "=") player.camera.zoom(0.9);
    else if (key === "-") player.camera.zoom(1 / 0.9);
    else if (key in flyKeys) player.camera.fly(...flyKeys[key]!);
    else if (key === "c") return snap((Number(camera.value || -1) + 1) % Math.max(1, player.cameras.length));
    else if (/^[1-9]$/.test(key)) return snap(Number(key) - 1);
    else if (key === "i") return toggleStats();
    else if (key === "l") return toggleLoop();
    else if (key === "f") return fullscreen();
    else return;
    e.preventDefault();
    if (key.startsWith("arrow") || key === "+" || key === "=" || key === "-" || key in flyKeys) moved();
  });

  const refresh = () => {
    const shown = Math.max(0, player.current + 1);
    time.value = player.still ? "still" : `${(shown / m.fps).toFixed(2)} / ${m.durationS.toFixed(2)} s`;
    if (document.activeElement !== camera) showCamera(); // a deep link may have moved the view
    if (document.activeElement !== seek && !player.still)
      seek.value = String(Math.floor(Math.max(0, player.current) / m.shape.gopSize));
    if (!stats.hidden) stats.textContent = player.stats.lines(player.bufferS()).join("\n");
    if (player.stats.shown && !poster.dataset.done) {
      poster.dataset.done = "1";
      poster.hidden = true;
      if (poster.src) URL.revokeObjectURL(poster.src);
    }
    if (player.ended && !player.paused && !player.loop) {
      play.textContent = "Replay";
      play.setAttribute("aria-label", "Replay");
    }
    setTimeout(refresh, 250);
  };
  refresh();
}

/** A quality-menu entry: the rung's id, its rate and, where the manifest says it, its PSNR (against the capture
 * where the packager knew it, else against the uncompressed model). */
export function rungLabel(r: Rung): string {
  const value = r.truthPsnr ?? r.renderPsnr;
  const db = value === null ? "" : `, ${value.toFixed(1)} dB`;
  return `${r.id} (${Math.round(r.bandwidth / 1e3)} kbit/s${db})`;
}
