// The caps of stgs/limits.py that the page applies to what it fetches (docs/ARCHITECTURE.md: sizes are checked before
// allocation). tests/web/test_contracts.py holds every value here equal to the Python one of the same name.
export const MAX_CAPACITY = 4194304;
export const MAX_GOP_SIZE = 1024;
export const MAX_WINDOW = 16;
export const MAX_PE_FREQS = 16;
export const MIN_FPS = 1.0;
export const MAX_FPS = 1000.0;
export const MAX_GOPS = 100000;
export const MAX_IMAGE_SIDE = 16384;
export const MAX_PATH_CAMERAS = 100000;
export const MAX_MPD_BYTES = 1048576;
export const MAX_DOC_BYTES = 16777216;
export const MAX_TITLE_CHARS = 200;
export const MAX_DESCRIPTION_CHARS = 4000;
export const MAX_POSTER_BYTES = 4194304;
export const MAX_KEYFRAME_HEADER_BYTES = 1048576;
export const MAX_SEGMENT_BYTES = 1073741824;
export const MAX_INIT_BYTES = 1048576;
export const SEGMENT_SLACK = 1.25;
export const MAX_DURATION_S = 316224000.0;
export const MAX_TEMPLATE_NUMBER_WIDTH = 32;

// The page's own caps on a manifest's element counts (a hostile MPD must not make the page build huge tables).
export const MAX_ADAPTATION_SETS = 16;
export const MAX_REPRESENTATIONS = 32;
