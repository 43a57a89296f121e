// The presentation clock: which frame the wall clock asks for. It starts when the frame it waits for is ready,
// runs at the scene's frame rate times the playback speed, skips (drops) frames it passed that are not the newest
// ready one, and stops at the next frame when nothing new is ready (a stall), to start again when that frame
// arrives.
export const SPEEDS = [0.25, 0.5, 1, 1.5, 2] as const;

export class PresentationClock {
  /** The frame the clock (re)starts at. */
  frame = 0;
  /** When it started (ms, the animation frame's time), or -1 while stopped. */
  private start = -1;
  /** Playback speed (one of SPEEDS): scene seconds per wall-clock second. */
  speed = 1;

  constructor(private readonly fps: number) {}

  restart(frame: number): void {
    this.frame = frame;
    this.start = -1;
  }

  /** The newest ready frame after `current` that the clock has reached (-1: none), and whether the clock has
   * just stopped for want of one (a stall). */
  next(
    now: number,
    current: number,
    total: number,
    ready: (frame: number) => boolean,
  ): { frame: number; stalled: boolean } {
    if (this.start < 0 && ready(this.frame)) this.start = now;
    const elapsed = ((now - this.start) / 1e3) * this.fps * this.speed;
    const due = this.start < 0 ? this.frame : this.frame + Math.floor(elapsed);
    const target = Math.min(due, total - 1);
    for (let f = target; f > current; f--) if (ready(f)) return { frame: f, stalled: false };
    if (target > current && this.start >= 0) {
      this.restart(current + 1);
      return { frame: -1, stalled: true };
    }
    return { frame: -1, stalled: false };
  }
}
