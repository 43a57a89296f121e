// Deep links: the page URL's fragment names a moment and a viewpoint, `#t=SECONDS&cam=VIEW`, where VIEW is a scene
// camera's name or the orbit's pose (ViewerCamera.orbitPose). "Copy link" writes the fragment of what is on
// screen; opening a page with one lands there. A fragment that does not hold up is ignored with a console warning.
import type { Player } from "./player";

/** Longest fragment read (a pose is about a hundred characters; a camera name a few dozen). */
const MAX_FRAGMENT_CHARS = 1000;

/** The fragment (without "#") of the frame on screen and the view it is seen from. */
export function linkFragment(player: Player): string {
  const pose = player.camera.pose;
  const cam = pose ? pose.name : player.camera.orbitPose();
  if (player.still) return new URLSearchParams({ cam }).toString(); // no time: a still has one moment
  return new URLSearchParams({ t: player.shownTimeS().toFixed(3), cam }).toString();
}

/** Go to the moment and the view `hash` names (location.hash); returns the warnings for what it ignored. */
export function applyLink(player: Player, hash: string): string[] {
  const text = hash.replace(/^#/, "");
  if (!text) return [];
  if (text.length > MAX_FRAGMENT_CHARS) return [`the link's fragment is longer than ${MAX_FRAGMENT_CHARS} characters`];
  const params = new URLSearchParams(text);
  const warnings: string[] = [];
  const cam = params.get("cam");
  if (cam !== null) {
    const index = player.cameras.findIndex((c) => c.name === cam);
    if (index >= 0) player.snapTo(index);
    else {
      try {
        player.camera.setOrbitPose(cam);
        player.invalidate();
      } catch (err) {
        const known = player.cameras.length
          ? `; the scene's cameras: ${player.cameras.map((c) => c.name).join(", ")}`
          : "";
        warnings.push(
          `cam=${cam.slice(0, 80)} is neither a camera of this scene nor a pose (${(err as Error).message})${known}`,
        );
      }
    }
  }
  const t = params.get("t");
  if (t !== null && player.still) warnings.push(`t=${t.slice(0, 40)} is ignored: a still scene has no timeline`);
  else if (t !== null) {
    const seconds = Number(t);
    if (t.trim() === "" || !Number.isFinite(seconds) || seconds < 0 || seconds > player.manifest.durationS)
      warnings.push(`t=${t.slice(0, 40)} is not a time in the scene (0..${player.manifest.durationS.toFixed(2)} s)`);
    else player.seekTime(seconds);
  }
  return warnings;
}
