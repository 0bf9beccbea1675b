/* The C API on the host: the firmware query localized through the x86-64 static library at
 * capacities 256 and 1024 (the reply bytes and the correspondences digest must be the host's at
 * that capacity, firmware/data/reply.hex and reply-1024.hex: the same pose as the Rust firmware;
 * each capacity has its own acceptance rule, so the confidence differs), and every error path. Each
 * gomatch_error that a check expects is recorded, and the test fails unless every code but
 * GOMATCH_ERROR_INTERNAL (which no input reaches: it would be a bug) was seen.
 *
 *   host_test MODEL_BLOB MAP_BLOB REPLY_HEX_256 REPLY_HEX_1024   (capi/test/run.sh builds and runs it)
 */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "gomatch.h"
#include "../example/query.h"

static int passed, failed;
static int reached[100];

static void check(int ok, const char *what, int line) {
  if (ok) {
    passed++;
  } else {
    failed++;
    fprintf(stderr, "FAILED (line %d): %s\n", line, what);
  }
}
#define CHECK(cond) check((cond), #cond, __LINE__)
/* `call` returns `code`; the code counts as reached. */
#define EXPECT(call, code)                                                                     \
  do {                                                                                         \
    gomatch_error got_ = (call);                                                               \
    if (got_ < 100) reached[got_] = 1;                                                         \
    if (got_ != (code))                                                                        \
      fprintf(stderr, "  got %u (%s), expected %u (%s)\n", (unsigned)got_,                     \
              gomatch_error_str(got_), (unsigned)(code), gomatch_error_str(code));             \
    check(got_ == (code), #call " == " #code, __LINE__);                                       \
  } while (0)

typedef struct {
  uint8_t *bytes;
  size_t len;
} buffer;

static buffer read_file(const char *path) {
  buffer b = {0, 0};
  FILE *f = fopen(path, "rb");
  if (!f) {
    perror(path);
    exit(2);
  }
  fseek(f, 0, SEEK_END);
  b.len = (size_t)ftell(f);
  fseek(f, 0, SEEK_SET);
  b.bytes = malloc(b.len + 16);
  if (!b.bytes || fread(b.bytes, 1, b.len, f) != b.len) {
    perror(path);
    exit(2);
  }
  fclose(f);
  return b;
}

static buffer copy(buffer b) {
  buffer c = {malloc(b.len + 16), b.len};
  memcpy(c.bytes, b.bytes, b.len);
  return c;
}

/* CRC-32 (IEEE) of the blob envelope's payload. */
static uint32_t crc32(const uint8_t *p, size_t n) {
  uint32_t crc = 0xFFFFFFFFu;
  for (size_t i = 0; i < n; i++) {
    crc ^= p[i];
    for (int k = 0; k < 8; k++) crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
  }
  return ~crc;
}

/* Envelope: magic (4), version (u16), reserved (u16), payload length (u32), CRC-32 (u32). */
enum { HEADER_BYTES = 16 };
static void fix_checksum(buffer b) {
  uint32_t crc = crc32(b.bytes + HEADER_BYTES, b.len - HEADER_BYTES);
  for (int i = 0; i < 4; i++) b.bytes[12 + i] = (uint8_t)(crc >> (8 * i));
}

/* The host's reply bytes (hex) and digest at one capacity, from its reply file. */
typedef struct {
  char reply[1024];
  char digest[16];
} expected_reply;

static void read_expected(const char *path, expected_reply *expected) {
  FILE *f = fopen(path, "r");
  if (!f) {
    perror(path);
    exit(2);
  }
  char line[512];
  while (fgets(line, sizeof line, f)) {
    line[strcspn(line, "\n")] = 0;
    const char *colon = strrchr(line, ' ');
    if (!colon) continue;
    if (strncmp(line, "reply bytes", 11) == 0) strcat(expected->reply, colon + 1);
    if (strncmp(line, "correspondences digest", 22) == 0)
      snprintf(expected->digest, sizeof expected->digest, "%s", colon + 1);
  }
  fclose(f);
  CHECK(strlen(expected->reply) > 0 && strlen(expected->digest) == 8);
}

static void hex(const uint8_t *bytes, size_t len, char *out) {
  for (size_t i = 0; i < len; i++) sprintf(out + 2 * i, "%02x", bytes[i]);
  out[2 * len] = 0;
}

static gomatch_model model;
static gomatch_map map;

static gomatch_query firmware_query(void) {
  gomatch_query q = {
      .keypoints = QUERY_KEYPOINTS,
      .keypoint_count = QUERY_KEYPOINT_COUNT,
      .camera = QUERY_CAMERA,
      .views = {.selection = GOMATCH_VIEWS_IMAGE_IDS, .image_id_count = QUERY_IMAGE_ID_COUNT},
  };
  memcpy(q.views.image_ids, QUERY_IMAGE_IDS, sizeof QUERY_IMAGE_IDS);
  return q;
}

/* A workspace of `capacity` in fresh heap memory (malloc aligns to 16). */
static gomatch_localizer *workspace(uint32_t capacity, void **memory) {
  size_t bytes = gomatch_localizer_bytes(capacity);
  *memory = malloc(bytes);
  gomatch_localizer *localizer = NULL;
  EXPECT(gomatch_localizer_init(*memory, bytes, capacity, &localizer), GOMATCH_OK);
  return localizer;
}

/* The reply message to the last localization, as hex. */
static void reply_hex(const gomatch_localizer *localizer, char *out) {
  uint8_t reply[GOMATCH_LINK_REPLY_BYTES];
  size_t len = 0;
  EXPECT(gomatch_link_reply(localizer, QUERY_REQUEST_ID, GOMATCH_REPLY_MESSAGE, reply, sizeof reply,
                            &len),
         GOMATCH_OK);
  hex(reply, len, out);
}

static void test_strings(void) {
  const uint32_t codes[] = {0,  1,  2,  3,  4,  5,  6,  7,  8,  10, 11, 12, 13,
                            14, 15, 16, 20, 21, 22, 23, 24, 25, 26, 27, 99};
  size_t n = sizeof codes / sizeof codes[0];
  for (size_t i = 0; i < n; i++) {
    CHECK(strcmp(gomatch_error_str(codes[i]), "unknown error") != 0);
    for (size_t j = 0; j < i; j++)
      CHECK(strcmp(gomatch_error_str(codes[i]), gomatch_error_str(codes[j])) != 0);
  }
  CHECK(strcmp(gomatch_error_str(9), "unknown error") == 0);
  CHECK(strcmp(gomatch_error_str(UINT32_MAX), "unknown error") == 0);
  CHECK(strcmp(gomatch_failure_str(GOMATCH_FAILURE_LOW_CONFIDENCE), "low confidence") == 0);
  CHECK(strcmp(gomatch_failure_str(8), "unknown failure") == 0);
}

static void test_blobs(buffer model_blob, buffer map_blob) {
  static _Alignas(8) uint8_t raw[sizeof(gomatch_model) + 8];
  EXPECT(gomatch_model_open(NULL, model_blob.bytes, model_blob.len), GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_model_open(&model, NULL, model_blob.len), GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_map_open(NULL, map_blob.bytes, map_blob.len), GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_map_open(&map, NULL, 0), GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_model_open((gomatch_model *)(void *)(raw + 4), model_blob.bytes, model_blob.len),
         GOMATCH_ERROR_MISALIGNED);
  EXPECT(gomatch_map_open((gomatch_map *)(void *)(raw + 4), map_blob.bytes, map_blob.len),
         GOMATCH_ERROR_MISALIGNED);
  EXPECT(gomatch_model_open(&model, model_blob.bytes, SIZE_MAX), GOMATCH_ERROR_INVALID_ARGUMENT);
  EXPECT(gomatch_model_open(&model, model_blob.bytes, 10), GOMATCH_ERROR_BLOB_TRUNCATED);
  EXPECT(gomatch_model_open(&model, model_blob.bytes, 0), GOMATCH_ERROR_BLOB_TRUNCATED);
  EXPECT(gomatch_map_open(&map, map_blob.bytes, map_blob.len - 1), GOMATCH_ERROR_BLOB_TRUNCATED);
  EXPECT(gomatch_model_open(&model, map_blob.bytes, map_blob.len), GOMATCH_ERROR_BLOB_MAGIC);
  EXPECT(gomatch_map_open(&map, model_blob.bytes, model_blob.len), GOMATCH_ERROR_BLOB_MAGIC);

  buffer b = copy(map_blob);
  b.bytes[4] ^= 0x40; /* version */
  EXPECT(gomatch_map_open(&map, b.bytes, b.len), GOMATCH_ERROR_BLOB_VERSION);
  memcpy(b.bytes, map_blob.bytes, b.len);
  b.bytes[6] = 1; /* reserved */
  EXPECT(gomatch_map_open(&map, b.bytes, b.len), GOMATCH_ERROR_BLOB_HEADER);
  memcpy(b.bytes, map_blob.bytes, b.len);
  b.bytes[b.len] = 0; /* one byte after the payload */
  EXPECT(gomatch_map_open(&map, b.bytes, b.len + 1), GOMATCH_ERROR_BLOB_HEADER);
  b.bytes[b.len - 7] ^= 0x10; /* a payload byte */
  EXPECT(gomatch_map_open(&map, b.bytes, b.len), GOMATCH_ERROR_BLOB_CHECKSUM);
  /* A points array of 2^32 - 1 bytes: the payload does not decode, the checksum holds. */
  memcpy(b.bytes, map_blob.bytes, b.len);
  memcpy(b.bytes + HEADER_BYTES, "\xff\xff\xff\xff\x0f", 5);
  fix_checksum(b);
  EXPECT(gomatch_map_open(&map, b.bytes, b.len), GOMATCH_ERROR_BLOB_MALFORMED);
  free(b.bytes);

  b = copy(model_blob);
  b.bytes[model_blob.len / 2] ^= 0x01;
  EXPECT(gomatch_model_open(&model, b.bytes, b.len), GOMATCH_ERROR_BLOB_CHECKSUM);
  /* The configuration's encoder_blocks (after feature_dim's two varint bytes): 200 blocks. */
  memcpy(b.bytes, model_blob.bytes, b.len);
  b.bytes[HEADER_BYTES + 2] = 200;
  fix_checksum(b);
  EXPECT(gomatch_model_open(&model, b.bytes, b.len), GOMATCH_ERROR_MODEL_UNSUPPORTED);
  /* A tensor table cut short: a byte of the last tensor's bias removed. */
  memcpy(b.bytes, model_blob.bytes, b.len);
  uint32_t payload = (uint32_t)(b.len - HEADER_BYTES - 1);
  for (int i = 0; i < 4; i++) b.bytes[8 + i] = (uint8_t)(payload >> (8 * i));
  b.len -= 1;
  fix_checksum(b);
  EXPECT(gomatch_model_open(&model, b.bytes, b.len), GOMATCH_ERROR_BLOB_MALFORMED);
  free(b.bytes);

  /* A failed open leaves the handle unopened. */
  gomatch_model unopened;
  memset(&unopened, 0xff, sizeof unopened);
  EXPECT(gomatch_model_open(&unopened, model_blob.bytes, 10), GOMATCH_ERROR_BLOB_TRUNCATED);
  CHECK(unopened._opened == 0);

  EXPECT(gomatch_model_open(&model, model_blob.bytes, model_blob.len), GOMATCH_OK);
  EXPECT(gomatch_map_open(&map, map_blob.bytes, map_blob.len), GOMATCH_OK);
}

static void test_workspace(void) {
  gomatch_localizer *localizer = NULL;
  CHECK(gomatch_localizer_bytes(128) == GOMATCH_LOCALIZER_BYTES_128);
  CHECK(gomatch_localizer_bytes(256) == GOMATCH_LOCALIZER_BYTES_256);
  CHECK(gomatch_localizer_bytes(1024) == GOMATCH_LOCALIZER_BYTES_1024);
  CHECK(gomatch_localizer_bytes(512) == 0 && gomatch_localizer_bytes(0) == 0);
  uint8_t *memory = malloc(GOMATCH_LOCALIZER_BYTES_128 + 8);
  EXPECT(gomatch_localizer_init(memory, GOMATCH_LOCALIZER_BYTES_128, 512, &localizer),
         GOMATCH_ERROR_UNSUPPORTED_CAPACITY);
  EXPECT(gomatch_localizer_init(NULL, GOMATCH_LOCALIZER_BYTES_128, 128, &localizer),
         GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_localizer_init(memory, GOMATCH_LOCALIZER_BYTES_128, 128, NULL),
         GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_localizer_init(memory, GOMATCH_LOCALIZER_BYTES_128, 256, NULL),
         GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_localizer_init(memory, GOMATCH_LOCALIZER_BYTES_128, 1024, NULL),
         GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_localizer_init(memory + 4, GOMATCH_LOCALIZER_BYTES_128, 128, &localizer),
         GOMATCH_ERROR_MISALIGNED);
  EXPECT(gomatch_localizer_init(memory, GOMATCH_LOCALIZER_BYTES_128 - 1, 128, &localizer),
         GOMATCH_ERROR_WORKSPACE_TOO_SMALL);
  EXPECT(gomatch_localizer_init(memory, GOMATCH_LOCALIZER_BYTES_128, 256, &localizer),
         GOMATCH_ERROR_WORKSPACE_TOO_SMALL);
  CHECK(localizer == NULL);

  /* Memory never initialised (zeroed, or garbage) is not a workspace. */
  memset(memory, 0, GOMATCH_LOCALIZER_BYTES_128);
  gomatch_query query = firmware_query();
  gomatch_result result;
  size_t len = 0;
  uint32_t digest = 0;
  EXPECT(gomatch_localize((gomatch_localizer *)(void *)memory, &model, &map, &query, &result),
         GOMATCH_ERROR_NOT_INITIALIZED);
  EXPECT(gomatch_inliers((gomatch_localizer *)(void *)memory, NULL, 0, &len),
         GOMATCH_ERROR_NOT_INITIALIZED);
  EXPECT(gomatch_localize((gomatch_localizer *)(void *)(memory + 4), &model, &map, &query,
                          &result),
         GOMATCH_ERROR_MISALIGNED);

  /* A fresh workspace has no result, no inliers and the digest of no correspondences. */
  EXPECT(gomatch_localizer_init(memory, GOMATCH_LOCALIZER_BYTES_128, 128, &localizer), GOMATCH_OK);
  CHECK((void *)localizer == (void *)memory);
  uint8_t reply[GOMATCH_LINK_REPLY_BYTES];
  EXPECT(gomatch_link_reply(localizer, 1, GOMATCH_REPLY_FRAME, reply, sizeof reply, &len),
         GOMATCH_ERROR_NO_RESULT);
  EXPECT(gomatch_inliers(localizer, NULL, 0, &len), GOMATCH_OK);
  CHECK(len == 0);
  EXPECT(gomatch_correspondences_digest(localizer, &digest), GOMATCH_OK);
  CHECK(digest == 0x811c9dc5u);

  /* The firmware query has 235 keypoints: too many for 128; its first 128 are not. */
  EXPECT(gomatch_localize(localizer, &model, &map, &query, &result),
         GOMATCH_ERROR_TOO_MANY_KEYPOINTS);
  CHECK(!result.localized && result.matches_mutual == 0);
  /* The refusal is a reply of its own: Response { id: Some(1), body: Error(..) }. */
  EXPECT(gomatch_link_reply(localizer, 1, GOMATCH_REPLY_MESSAGE, reply, sizeof reply, &len),
         GOMATCH_OK);
  CHECK(len >= 3 && reply[0] == 1 && reply[1] == 1 && reply[2] == 2);
  query.keypoint_count = SIZE_MAX;
  EXPECT(gomatch_localize(localizer, &model, &map, &query, &result),
         GOMATCH_ERROR_TOO_MANY_KEYPOINTS);
  query.keypoint_count = 128;
  EXPECT(gomatch_localize(localizer, &model, &map, &query, &result), GOMATCH_OK);
  CHECK(result.views_used + result.views_skipped == QUERY_IMAGE_ID_COUNT);
  free(memory);
}

/* The firmware query at `capacity`: the host's reply bytes and digest. */
static void test_firmware_query(uint32_t capacity, const expected_reply *expected) {
  void *memory;
  gomatch_localizer *localizer = workspace(capacity, &memory);
  gomatch_query query = firmware_query();
  gomatch_result result;
  EXPECT(gomatch_localize(localizer, &model, &map, &query, &result), GOMATCH_OK);
  printf("capacity %u: %s, %u mutual / %u classified / %u merged matches, %u inliers, "
         "confidence %.4f; q = %.6f %.6f %.6f %.6f, t = %.6f %.6f %.6f\n",
         capacity, result.localized ? "localized" : gomatch_failure_str(result.failure),
         result.matches_mutual, result.matches_classified, result.matches_merged, result.inliers,
         result.confidence, result.pose.rotation[0], result.pose.rotation[1],
         result.pose.rotation[2], result.pose.rotation[3], result.pose.translation[0],
         result.pose.translation[1], result.pose.translation[2]);
  CHECK(result.localized && result.failure == GOMATCH_FAILURE_NONE);
  CHECK(result.views_used == QUERY_IMAGE_ID_COUNT && result.views_skipped == 0);
  CHECK(result.confidence >= result.min_confidence && result.confidence <= 1.0f);
  double norm = 0;
  for (int i = 0; i < 4; i++) norm += result.pose.rotation[i] * result.pose.rotation[i];
  CHECK(fabs(norm - 1.0) < 1e-12 && result.pose.rotation[0] >= 0);

  char got[1024];
  reply_hex(localizer, got);
  CHECK(strcmp(got, expected->reply) == 0);
  uint32_t digest = 0;
  EXPECT(gomatch_correspondences_digest(localizer, &digest), GOMATCH_OK);
  char digest_hex[16];
  snprintf(digest_hex, sizeof digest_hex, "%08x", digest);
  CHECK(strcmp(digest_hex, expected->digest) == 0);
  printf("capacity %u: reply bytes %s the host's, digest %s\n", capacity,
         strcmp(got, expected->reply) == 0 ? "identical to" : "DIFFERENT from", digest_hex);

  /* The reply frame: COBS, no zero inside, one at the end. */
  uint8_t frame[GOMATCH_LINK_REPLY_BYTES];
  size_t len = 0;
  EXPECT(gomatch_link_reply(localizer, QUERY_REQUEST_ID, GOMATCH_REPLY_FRAME, frame, sizeof frame,
                            &len),
         GOMATCH_OK);
  CHECK(len > strlen(expected->reply) / 2 + 4 && len <= GOMATCH_LINK_REPLY_BYTES);
  CHECK(frame[len - 1] == 0 && memchr(frame, 0, len - 1) == NULL);
  EXPECT(gomatch_link_reply(localizer, 1, GOMATCH_REPLY_FRAME, frame, 3, &len),
         GOMATCH_ERROR_BUFFER_TOO_SMALL);
  CHECK(len > 3);
  EXPECT(gomatch_link_reply(localizer, 1, GOMATCH_REPLY_FRAME, NULL, sizeof frame, &len),
         GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_link_reply(localizer, 1, 7, frame, sizeof frame, &len),
         GOMATCH_ERROR_INVALID_ARGUMENT);
  EXPECT(gomatch_link_reply(localizer, 1, GOMATCH_REPLY_FRAME, frame, sizeof frame, NULL),
         GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_link_reply(NULL, 1, GOMATCH_REPLY_FRAME, frame, sizeof frame, &len),
         GOMATCH_ERROR_NULL_POINTER);

  /* The inliers: their number first, then all of them. */
  size_t count = 0;
  EXPECT(gomatch_inliers(localizer, NULL, 0, &count), GOMATCH_ERROR_BUFFER_TOO_SMALL);
  CHECK(count == result.inliers && count >= 4);
  gomatch_inlier *inliers = malloc((count + 1) * sizeof *inliers);
  EXPECT(gomatch_inliers(localizer, inliers, 1, &count), GOMATCH_ERROR_BUFFER_TOO_SMALL);
  EXPECT(gomatch_inliers(localizer, NULL, count, &count), GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_inliers(localizer, (gomatch_inlier *)(void *)((uint8_t *)inliers + 2), count,
                         &count),
         GOMATCH_ERROR_MISALIGNED);
  EXPECT(gomatch_inliers(localizer, inliers, count, NULL), GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_inliers(localizer, inliers, count + 1, &count), GOMATCH_OK);
  CHECK(count == result.inliers);
  for (size_t i = 0; i < count; i++) {
    CHECK(inliers[i].keypoint < QUERY_KEYPOINT_COUNT);
    CHECK(inliers[i].probability > 0.5f && inliers[i].probability <= 1.0f);
    if (i > 0) CHECK(inliers[i - 1].keypoint < inliers[i].keypoint);
  }
  free(inliers);
  EXPECT(gomatch_correspondences_digest(localizer, NULL), GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_correspondences_digest(NULL, &digest), GOMATCH_ERROR_NULL_POINTER);

  /* Deterministic: the same bytes again, also after another query in between. */
  gomatch_query other = query;
  other.keypoint_count = 100;
  other.views.image_id_count = 3;
  EXPECT(gomatch_localize(localizer, &model, &map, &other, &result), GOMATCH_OK);
  char between[1024];
  reply_hex(localizer, between);
  CHECK(strcmp(between, expected->reply) != 0);
  EXPECT(gomatch_localize(localizer, &model, &map, &query, &result), GOMATCH_OK);
  reply_hex(localizer, got);
  CHECK(strcmp(got, expected->reply) == 0);

  /* A query refused before the localizer runs leaves no correspondences of earlier calls. */
  gomatch_query refused = query;
  refused.views.image_id_count = GOMATCH_MAX_VIEWS + 1;
  EXPECT(gomatch_localize(localizer, &model, &map, &refused, &result), GOMATCH_ERROR_TOO_MANY_VIEWS);
  EXPECT(gomatch_inliers(localizer, NULL, 0, &count), GOMATCH_OK);
  CHECK(count == 0);
  EXPECT(gomatch_correspondences_digest(localizer, &digest), GOMATCH_OK);
  CHECK(digest == 0x811c9dc5u);
  EXPECT(gomatch_localize(localizer, &model, &map, &query, &result), GOMATCH_OK);

  /* Views near a prior: the pose found, its 3 nearest views. */
  gomatch_query near = query;
  near.views.selection = GOMATCH_VIEWS_NEAR_PRIOR;
  near.views.prior = result.pose;
  near.views.k = 3;
  near.views.max_angle_deg = 30;
  EXPECT(gomatch_localize(localizer, &model, &map, &near, &result), GOMATCH_OK);
  CHECK(result.views_used + result.views_skipped == 3);
  free(memory);
}

/* Queries the API refuses, and valid ones that are not localized. */
static void test_query_errors(void) {
  void *memory;
  gomatch_localizer *localizer = workspace(256, &memory);
  gomatch_query good = firmware_query(), q;
  gomatch_result result;
  gomatch_model unopened_model;
  gomatch_map unopened_map;
  memset(&unopened_model, 0, sizeof unopened_model);
  memset(&unopened_map, 0, sizeof unopened_map);
  uint8_t reply[GOMATCH_LINK_REPLY_BYTES];
  size_t len = 0;

  EXPECT(gomatch_localize(localizer, &model, &map, &good, NULL), GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_localize(NULL, &model, &map, &good, &result), GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_localize(localizer, NULL, &map, &good, &result), GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_localize(localizer, &model, NULL, &good, &result), GOMATCH_ERROR_NULL_POINTER);
  EXPECT(gomatch_localize(localizer, &unopened_model, &map, &good, &result),
         GOMATCH_ERROR_NOT_INITIALIZED);
  EXPECT(gomatch_localize(localizer, &model, &unopened_map, &good, &result),
         GOMATCH_ERROR_NOT_INITIALIZED);
  EXPECT(gomatch_localize(localizer, &model, &map, NULL, &result), GOMATCH_ERROR_NULL_POINTER);
  /* Refused before the query was read: nothing to reply. */
  EXPECT(gomatch_link_reply(localizer, 1, GOMATCH_REPLY_FRAME, reply, sizeof reply, &len),
         GOMATCH_ERROR_NO_RESULT);

  q = good;
  q.keypoints = NULL;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_NULL_POINTER);
  static _Alignas(8) uint8_t shifted[8 * QUERY_KEYPOINT_COUNT + 8];
  memcpy(shifted + 2, QUERY_KEYPOINTS, sizeof QUERY_KEYPOINTS);
  q.keypoints = (const float(*)[2])(const void *)(shifted + 2);
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_MISALIGNED);

  float (*kp)[2] = malloc(sizeof QUERY_KEYPOINTS);
  memcpy(kp, QUERY_KEYPOINTS, sizeof QUERY_KEYPOINTS);
  q = good;
  q.keypoints = (const float(*)[2])kp;
  kp[7][0] = NAN;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_NON_FINITE_KEYPOINT);
  EXPECT(gomatch_link_reply(localizer, 1, GOMATCH_REPLY_MESSAGE, reply, sizeof reply, &len),
         GOMATCH_OK);
  CHECK(len >= 3 && reply[2] == 2);
  kp[7][0] = 10;
  kp[200][1] = -INFINITY;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_NON_FINITE_KEYPOINT);
  free(kp);

  q = good;
  q.camera.model = 9;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_INVALID_CAMERA);
  q.camera.model = UINT32_MAX;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_INVALID_CAMERA);
  q = good;
  q.camera.params[1] = 0; /* fy */
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_INVALID_CAMERA);
  q = good;
  q.camera.params[5] = NAN; /* k2 */
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_INVALID_CAMERA);

  /* A lens that folds 0.19 px from the principal point: keypoint 0 lies beyond. */
  const gomatch_camera folding = {GOMATCH_CAMERA_OPENCV, 640, 480,
                                  {500, 500, 320, 240, -1e6, 1e6, 0, 0}};
  float pixels[20][2];
  for (int i = 0; i < 20; i++) {
    pixels[i][0] = (float)(10 + 31 * i);
    pixels[i][1] = (float)(10 + 23 * i);
  }
  q = good;
  q.camera = folding;
  q.keypoints = (const float(*)[2])pixels;
  q.keypoint_count = 20;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result),
         GOMATCH_ERROR_DISTORTION_NOT_INVERTIBLE);
  /* Strong tangential distortion: the undistortion of keypoint 3 does not converge. */
  const gomatch_camera tangential = {GOMATCH_CAMERA_OPENCV, 640, 480, {500, 500, 320, 240, 0, 0, 1, 1}};
  for (int i = 0; i < 20; i++) {
    pixels[i][0] = 640;
    pixels[i][1] = 480;
  }
  pixels[3][0] = 100;
  pixels[3][1] = 400;
  q.camera = tangential;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_UNDISTORTION_FAILED);

  q = good;
  q.views.image_id_count = GOMATCH_MAX_VIEWS + 1;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_TOO_MANY_VIEWS);
  q.views.image_id_count = UINT32_MAX;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_TOO_MANY_VIEWS);
  q = good;
  q.views.image_ids[4] = 999999;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_UNKNOWN_IMAGE);
  q = good;
  q.views.selection = 2;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_INVALID_ARGUMENT);

  gomatch_query near = good;
  near.views.selection = GOMATCH_VIEWS_NEAR_PRIOR;
  near.views.prior = (gomatch_pose){{1, 0, 0, 0}, {0, 0, 0}};
  near.views.k = 3;
  near.views.max_angle_deg = 30;
  q = near;
  q.views.k = GOMATCH_MAX_VIEWS + 1;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_TOO_MANY_VIEWS);
  q = near;
  q.views.prior.rotation[0] = 0;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_INVALID_PRIOR);
  q = near;
  q.views.prior.translation[2] = NAN;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_INVALID_PRIOR);
  q = near;
  q.views.prior.rotation[1] = INFINITY;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_INVALID_PRIOR);
  q = near;
  q.views.max_angle_deg = NAN;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_INVALID_PRIOR);
  q = near;
  q.views.max_angle_deg = -1;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_ERROR_INVALID_PRIOR);
  EXPECT(gomatch_localize(localizer, &model, &map, &near, &result), GOMATCH_OK);

  /* Valid queries that are not localized: typed failures with their counts. */
  q = good;
  q.keypoint_count = 5;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_OK);
  CHECK(!result.localized && result.failure == GOMATCH_FAILURE_TOO_FEW_KEYPOINTS);
  CHECK(result.needed == 10 && result.found == 5 && result.confidence == -1.0f);
  q = good;
  q.views.image_id_count = 0;
  EXPECT(gomatch_localize(localizer, &model, &map, &q, &result), GOMATCH_OK);
  CHECK(!result.localized && result.failure == GOMATCH_FAILURE_NO_VIEWS);
  size_t count = 1;
  EXPECT(gomatch_inliers(localizer, NULL, 0, &count), GOMATCH_OK);
  CHECK(count == 0);
  free(memory);
}

int main(int argc, char **argv) {
  if (argc != 5) {
    fprintf(stderr, "usage: %s MODEL_BLOB MAP_BLOB REPLY_HEX_256 REPLY_HEX_1024\n", argv[0]);
    return 2;
  }
  buffer model_blob = read_file(argv[1]), map_blob = read_file(argv[2]);
  static expected_reply at_256, at_1024;
  read_expected(argv[3], &at_256);
  read_expected(argv[4], &at_1024);

  test_strings();
  test_blobs(model_blob, map_blob);
  test_workspace();
  test_firmware_query(256, &at_256);
  test_firmware_query(1024, &at_1024);
  test_query_errors();

  static const unsigned codes[] = {0,  1,  2,  3,  4,  5,  6,  7,  8,  10, 11, 12,
                                   13, 14, 15, 16, 20, 21, 22, 23, 24, 25, 26, 27};
  for (size_t i = 0; i < sizeof codes / sizeof codes[0]; i++) {
    if (!reached[codes[i]]) fprintf(stderr, "error code %u never reached\n", codes[i]);
    CHECK(reached[codes[i]]);
  }
  free(model_blob.bytes);
  free(map_blob.bytes);
  printf("capi host test: %d passed, %d failed\n", passed, failed);
  return failed == 0 ? 0 : 1;
}
