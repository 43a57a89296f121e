// scene.json, what a catalogue shows of a scene (stgs pack; docs/PACKAGING.md, "The scene's face"): its title,
// description and poster. Read as data only: the title and description are shown as text, the poster's URL goes
// through the page's URL policy like any other.
import * as L from "./limits";

/** A poster path: relative, inside the scene's folder, a WebP file (stgs/server/catalogue.py holds the same rule). */
const POSTER_PATH = /^[\w.-]+(\/[\w.-]+)*\.webp$/;

export interface SceneFace {
  title: string;
  description: string;
  /** Absolute URL of the poster image, or null. */
  posterUrl: string | null;
}

/** The face of scene.json's document `doc` (fetched from `url`); throws a TypeError on a malformed one. */
export function parseSceneFace(doc: unknown, url: string): SceneFace {
  const d = doc as Record<string, unknown>;
  if (typeof d !== "object" || d === null || d.format !== "streamstgs-scene")
    throw new TypeError("scene.json is not a streamstgs-scene document");
  const { title, description = "", poster = null } = d;
  if (typeof title !== "string" || !title.trim() || title.length > L.MAX_TITLE_CHARS)
    throw new TypeError(`scene.json's title must be a string of 1..${L.MAX_TITLE_CHARS} characters`);
  if (typeof description !== "string" || description.length > L.MAX_DESCRIPTION_CHARS)
    throw new TypeError(`scene.json's description must be a string of at most ${L.MAX_DESCRIPTION_CHARS} characters`);
  if (poster !== null && (typeof poster !== "string" || !POSTER_PATH.test(poster) || /(^|\/)\.+(\/|$)/.test(poster)))
    throw new TypeError("scene.json's poster must be a relative path to a .webp file");
  return { title, description, posterUrl: poster === null ? null : new URL(poster, url).href };
}
