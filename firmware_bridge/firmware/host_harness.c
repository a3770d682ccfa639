/* Host-side harness for the reference C implementation (not for the microcontroller).
 *
 * The Python tests compile it with the system C compiler and drive it through stdin/stdout:
 *   harness decode   stdin: raw wire bytes, fed to the decoder one byte at a time;
 *                    stdout: one canonical line per accepted frame, "REJECT <reason>" per rejected
 *                    frame, then a STATS line.
 *   harness digest   like decode but prints only "DIGEST <crc32 of all canonical lines>" and STATS
 *                    (for million-frame fuzz runs).
 *   harness encode   stdin: canonical lines; stdout: the wire bytes of each, in hex, one per line.
 * Floats travel as their IEEE-754 bit patterns so both sides compare exactly.
 */
#include <inttypes.h>
#include <stdio.h>
#include <string.h>

#include "acesplat_bridge.h"

static const char *const REASONS[ACB_REJECT_COUNT] = {"overflow", "cobs", "short", "crc",
                                                      "version", "type", "length", "value"};

typedef union {
    uint32_t u;
    float f;
} bits_t;

static uint32_t fbits(float f) {
    bits_t b;
    b.f = f;
    return b.u;
}

static float bitsf(uint32_t u) {
    bits_t b;
    b.u = u;
    return b.f;
}

static int canonical(const acb_message_t *m, char *buf, size_t cap) {
    const acb_pose_t *p = &m->u.pose;
    const acb_status_t *s = &m->u.status;
    switch (m->type) {
        case ACB_MSG_POSE:
            return snprintf(buf, cap,
                            "POSE seq=%u ts=%" PRIu64 " frame=%" PRIu32 " pos=%08" PRIx32 ",%08" PRIx32 ",%08" PRIx32
                            " quat=%08" PRIx32 ",%08" PRIx32 ",%08" PRIx32 ",%08" PRIx32
                            " inliers=%u state=%u quality=%08" PRIx32 "\n",
                            (unsigned)m->seq, p->timestamp_us, p->frame_id, fbits(p->position[0]),
                            fbits(p->position[1]), fbits(p->position[2]), fbits(p->quat_wxyz[0]),
                            fbits(p->quat_wxyz[1]), fbits(p->quat_wxyz[2]), fbits(p->quat_wxyz[3]),
                            (unsigned)p->inliers, (unsigned)p->state, fbits(p->quality));
        case ACB_MSG_STATUS:
            return snprintf(buf, cap,
                            "STATUS seq=%u ts=%" PRIu64 " fps=%08" PRIx32 " latency=%08" PRIx32
                            " frames_dropped=%" PRIu32 " poses_dropped=%" PRIu32 " state=%u\n",
                            (unsigned)m->seq, s->timestamp_us, fbits(s->fps), fbits(s->latency_ms),
                            s->frames_dropped, s->poses_dropped, (unsigned)s->state);
        case ACB_MSG_COMMAND:
            return snprintf(buf, cap, "COMMAND seq=%u command=%u value=%08" PRIx32 "\n", (unsigned)m->seq,
                            (unsigned)m->u.command.command, fbits(m->u.command.value));
        default:
            return snprintf(buf, cap, "ACK seq=%u acked=%u command=%u result=%u\n", (unsigned)m->seq,
                            (unsigned)m->u.ack.acked_seq, (unsigned)m->u.ack.command, (unsigned)m->u.ack.result);
    }
}

static int run_decode(int print_lines) {
    static uint8_t chunk[65536];
    acb_decoder_t dec;
    acb_message_t msg;
    char line[512];
    uint32_t digest = 0;
    size_t n, i;
    int k;
    acb_decoder_init(&dec);
    while ((n = fread(chunk, 1, sizeof chunk, stdin)) > 0) {
        for (i = 0; i < n; i++) {
            acb_feed_result_t r = acb_decoder_feed(&dec, chunk[i], &msg);
            if (r == ACB_MESSAGE) {
                int len = canonical(&msg, line, sizeof line);
                digest = acb_crc32(digest, (const uint8_t *)line, (size_t)len);
                if (print_lines) fputs(line, stdout);
            } else if (r == ACB_REJECTED && print_lines) {
                printf("REJECT %s\n", REASONS[dec.last_reject]);
            }
        }
    }
    if (!print_lines) printf("DIGEST %08" PRIx32 "\n", digest);
    printf("STATS ok=%" PRIu32, dec.frames_ok);
    for (k = 0; k < ACB_REJECT_COUNT; k++) printf(" %s=%" PRIu32, REASONS[k], dec.rejected[k]);
    printf("\n");
    return 0;
}

static int parse_line(const char *line, acb_message_t *m) {
    unsigned seq, a, b, c, d;
    uint32_t f[8];
    memset(m, 0, sizeof *m);
    if (sscanf(line,
               "POSE seq=%u ts=%" SCNu64 " frame=%" SCNu32 " pos=%" SCNx32 ",%" SCNx32 ",%" SCNx32 " quat=%" SCNx32
               ",%" SCNx32 ",%" SCNx32 ",%" SCNx32 " inliers=%u state=%u quality=%" SCNx32,
               &seq, &m->u.pose.timestamp_us, &m->u.pose.frame_id, &f[0], &f[1], &f[2], &f[3], &f[4], &f[5], &f[6],
               &a, &b, &f[7]) == 13) {
        m->type = ACB_MSG_POSE;
        m->u.pose.position[0] = bitsf(f[0]);
        m->u.pose.position[1] = bitsf(f[1]);
        m->u.pose.position[2] = bitsf(f[2]);
        m->u.pose.quat_wxyz[0] = bitsf(f[3]);
        m->u.pose.quat_wxyz[1] = bitsf(f[4]);
        m->u.pose.quat_wxyz[2] = bitsf(f[5]);
        m->u.pose.quat_wxyz[3] = bitsf(f[6]);
        m->u.pose.inliers = (uint16_t)a;
        m->u.pose.state = (uint8_t)b;
        m->u.pose.quality = bitsf(f[7]);
    } else if (sscanf(line,
                      "STATUS seq=%u ts=%" SCNu64 " fps=%" SCNx32 " latency=%" SCNx32 " frames_dropped=%" SCNu32
                      " poses_dropped=%" SCNu32 " state=%u",
                      &seq, &m->u.status.timestamp_us, &f[0], &f[1], &m->u.status.frames_dropped,
                      &m->u.status.poses_dropped, &a) == 7) {
        m->type = ACB_MSG_STATUS;
        m->u.status.fps = bitsf(f[0]);
        m->u.status.latency_ms = bitsf(f[1]);
        m->u.status.state = (uint8_t)a;
    } else if (sscanf(line, "COMMAND seq=%u command=%u value=%" SCNx32, &seq, &a, &f[0]) == 3) {
        m->type = ACB_MSG_COMMAND;
        m->u.command.command = (uint8_t)a;
        m->u.command.value = bitsf(f[0]);
    } else if (sscanf(line, "ACK seq=%u acked=%u command=%u result=%u", &seq, &a, &c, &d) == 4) {
        m->type = ACB_MSG_ACK;
        m->u.ack.acked_seq = (uint16_t)a;
        m->u.ack.command = (uint8_t)c;
        m->u.ack.result = (uint8_t)d;
    } else {
        return 0;
    }
    m->seq = (uint16_t)seq;
    return 1;
}

static int run_encode(void) {
    char line[512];
    uint8_t wire[ACB_MAX_WIRE];
    acb_message_t m;
    size_t n, i;
    while (fgets(line, sizeof line, stdin)) {
        if (!parse_line(line, &m)) {
            fprintf(stderr, "cannot parse: %s", line);
            return 1;
        }
        n = acb_encode(&m, wire, sizeof wire);
        for (i = 0; i < n; i++) printf("%02x", wire[i]);
        printf("\n");
    }
    return 0;
}

int main(int argc, char **argv) {
    if (argc == 2 && strcmp(argv[1], "decode") == 0) return run_decode(1);
    if (argc == 2 && strcmp(argv[1], "digest") == 0) return run_decode(0);
    if (argc == 2 && strcmp(argv[1], "encode") == 0) return run_encode();
    fprintf(stderr, "usage: %s decode|digest|encode\n", argv[0]);
    return 2;
}
