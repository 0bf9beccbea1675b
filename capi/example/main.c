/* The gomatch localizer in a C firmware: opens the model and the map in flash, sets up the
   workspace in the board's PSRAM, localizes the firmware query (the same one the Rust
   firmware serves, query.h) and prints the pose, the inliers, and the device link's reply
   bytes, which firmware/cross_isa.sh compares with the host's.

   Exit status (as the Rust firmware's): 0 localized, 3 not localized, 4 pose refused (low
   confidence), 10 model invalid, 11 map invalid, 13 query refused, 12 reply not written. */
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include "board.h"
#include "gomatch.h"
#include "query.h"

/* The model and map blobs, embedded in .rodata (flash) at build time; CMake passes their
   paths. Read in place: they must stay where they are while the model and map are used. */
#define STR_(x) #x
#define STR(x) STR_(x)
__asm__(".section .rodata.gomatch_blobs, \"a\"\n"
        ".balign 8\n"
        "model_blob: .incbin \"" STR(GOMATCH_MODEL_PATH) "\"\n"
        "model_blob_end:\n"
        ".balign 8\n"
        "map_blob: .incbin \"" STR(GOMATCH_MAP_PATH) "\"\n"
        "map_blob_end:\n"
        ".previous\n");
extern const uint8_t model_blob[], model_blob_end[], map_blob[], map_blob_end[];

/* Keypoints per query and points per view. */
#define CAPACITY 256

/* The workspace, 1 MiB: in the board's PSRAM (a NOLOAD section: not copied or zeroed at
   start-up; gomatch_localizer_init needs neither). */
static _Alignas(GOMATCH_LOCALIZER_ALIGN) uint8_t workspace[GOMATCH_LOCALIZER_BYTES_256]
    __attribute__((section(".psram")));
static gomatch_model model;
static gomatch_map map;
static gomatch_inlier inliers[CAPACITY];

/* Output: a line is built in `line` and printed at once. */
static char line[160];
static size_t line_len;

static void put(const char *text) {
  while (*text && line_len + 1 < sizeof line) line[line_len++] = *text++;
}
static void put_u64(uint64_t v) {
  char digits[21];
  int n = 0;
  do {
    digits[n++] = (char)('0' + v % 10);
    v /= 10;
  } while (v);
  while (n) {
    char c[2] = {digits[--n], 0};
    put(c);
  }
}
static void put_hex(const uint8_t *bytes, size_t len) {
  static const char hex[] = "0123456789abcdef";
  for (size_t i = 0; i < len; i++) {
    char c[3] = {hex[bytes[i] >> 4], hex[bytes[i] & 15], 0};
    put(c);
  }
}
/* `v` with 6 decimals (|v| < 1.8e13). */
static void put_fixed(double v) {
  if (v < 0) {
    put("-");
    v = -v;
  }
  uint64_t micro = (uint64_t)(v * 1e6 + 0.5);
  put_u64(micro / 1000000);
  put(".");
  char frac[7];
  for (int i = 5; i >= 0; i--, micro /= 10) frac[i] = (char)('0' + micro % 10);
  frac[6] = 0;
  put(frac);
}
static void end_line(void) {
  line[line_len++] = '\n';
  line[line_len] = 0;
  board_print(line);
  line_len = 0;
}

static int fail(const char *what, gomatch_error error, int status) {
  put(what);
  put(": ");
  put(gomatch_error_str(error));
  end_line();
  return status;
}

/* Prints the reply to the query as numbered hex lines of 40 bytes, as the Rust firmware
   does, then the digest of the merged correspondences. */
static int print_reply(const gomatch_localizer *localizer) {
  uint8_t reply[GOMATCH_LINK_REPLY_BYTES];
  size_t len = 0;
  gomatch_error e = gomatch_link_reply(localizer, QUERY_REQUEST_ID, GOMATCH_REPLY_MESSAGE, reply,
                                       sizeof reply, &len);
  if (e != GOMATCH_OK) return fail("reply", e, 12);
  size_t lines = (len + 39) / 40;
  for (size_t i = 0; i < lines; i++) {
    put("reply bytes (timings cleared) ");
    put_u64(i + 1);
    put("/");
    put_u64(lines);
    put(": ");
    put_hex(reply + 40 * i, len - 40 * i < 40 ? len - 40 * i : 40);
    end_line();
  }
  uint32_t digest = 0;
  e = gomatch_correspondences_digest(localizer, &digest);
  if (e != GOMATCH_OK) return fail("digest", e, 12);
  const uint8_t be[4] = {(uint8_t)(digest >> 24), (uint8_t)(digest >> 16), (uint8_t)(digest >> 8),
                         (uint8_t)digest};
  put("correspondences digest: ");
  put_hex(be, 4);
  end_line();
  return 0;
}

int main(void) {
  uint32_t q16 = board_start_counter();
  put("SysTick: ");
  put_u64(q16);
  put("/65536 instructions per tick");
  end_line();

  gomatch_error e = gomatch_model_open(&model, model_blob, (size_t)(model_blob_end - model_blob));
  if (e != GOMATCH_OK) return fail("model", e, 10);
  e = gomatch_map_open(&map, map_blob, (size_t)(map_blob_end - map_blob));
  if (e != GOMATCH_OK) return fail("map", e, 11);
  gomatch_localizer *localizer = NULL;
  e = gomatch_localizer_init(workspace, sizeof workspace, CAPACITY, &localizer);
  if (e != GOMATCH_OK) return fail("workspace", e, 13);

  gomatch_query query = {
      .keypoints = QUERY_KEYPOINTS,
      .keypoint_count = QUERY_KEYPOINT_COUNT,
      .camera = QUERY_CAMERA,
      .views = {.selection = GOMATCH_VIEWS_IMAGE_IDS, .image_id_count = QUERY_IMAGE_ID_COUNT},
  };
  memcpy(query.views.image_ids, QUERY_IMAGE_IDS, sizeof QUERY_IMAGE_IDS);

  gomatch_result result;
  uint64_t start = board_instructions();
  e = gomatch_localize(localizer, &model, &map, &query, &result);
  uint64_t instructions = board_instructions() - start;
  if (e != GOMATCH_OK) return fail("query", e, 13);

  put("matches: ");
  put_u64(result.matches_mutual);
  put(" mutual, ");
  put_u64(result.matches_classified);
  put(" classified, ");
  put_u64(result.matches_merged);
  put(" merged, ");
  put_u64(result.inliers);
  put(" inliers; views used ");
  put_u64(result.views_used);
  end_line();
  if (result.localized) {
    put("pose (world to camera): q = ");
    for (int i = 0; i < 4; i++) {
      put_fixed(result.pose.rotation[i]);
      put(i < 3 ? " " : ", t = ");
    }
    for (int i = 0; i < 3; i++) {
      put_fixed(result.pose.translation[i]);
      put(i < 2 ? " " : "");
    }
    end_line();
  } else {
    put("not localized: ");
    put(gomatch_failure_str(result.failure));
    end_line();
  }
  put("confidence: ");
  put_fixed(result.confidence);
  put(" (accepted from ");
  put_fixed(result.min_confidence);
  put(")");
  end_line();

  size_t count = 0;
  e = gomatch_inliers(localizer, inliers, CAPACITY, &count);
  if (e != GOMATCH_OK) return fail("inliers", e, 12);
  for (size_t i = 0; i < count && i < 3; i++) {
    put("inlier: keypoint ");
    put_u64(inliers[i].keypoint);
    put(", map point ");
    put_u64(inliers[i].point);
    put(", probability ");
    put_fixed(inliers[i].probability);
    end_line();
  }

  int status = print_reply(localizer);
  if (status != 0) return status;
  put("instructions, whole query: ");
  put_u64(instructions);
  end_line();
  if (result.localized) status = 0;
  else if (result.failure == GOMATCH_FAILURE_LOW_CONFIDENCE) status = 4;
  else status = 3;
  put("exit status ");
  put_u64((uint64_t)status);
  end_line();
  return status;
}
