/* acesplat firmware bridge, protocol v1: reference implementation for the microcontroller side.
 * C99, no dynamic memory; see acesplat_bridge.h for the API and ../PROTOCOL.md for the bytes. */
#include "acesplat_bridge.h"

/* Largest body of a v1 message (POSE): encode works in a stack buffer of this size. */
#define ACB_LARGEST_BODY (ACB_HEADER_SIZE + ACB_POSE_PAYLOAD + ACB_CRC_SIZE)

typedef union {
    uint32_t u;
    float f;
} acb_f32_bits;

/* CRC-32 four bits at a time: a 64-byte table instead of 1 KiB, two lookups per byte. */
static const uint32_t acb_crc_nibble[16] = {
    0x00000000u, 0x1db71064u, 0x3b6e20c8u, 0x26d930acu, 0x76dc4190u, 0x6b6b51f4u, 0x4db26158u, 0x5005713cu,
    0xedb88320u, 0xf00f9344u, 0xd6d6a3e8u, 0xcb61b38cu, 0x9b64c2b0u, 0x86d3d2d4u, 0xa00ae278u, 0xbdbdf21cu,
};

uint32_t acb_crc32(uint32_t crc, const uint8_t *data, size_t len) {
    size_t i;
    crc = ~crc;
    for (i = 0; i < len; i++) {
        crc ^= data[i];
        crc = (crc >> 4) ^ acb_crc_nibble[crc & 0x0fu];
        crc = (crc >> 4) ^ acb_crc_nibble[crc & 0x0fu];
    }
    return ~crc;
}

/* ---- little-endian field access ---- */

static uint16_t rd16(const uint8_t *p) { return (uint16_t)(p[0] | (uint16_t)(p[1] << 8)); }

static uint32_t rd32(const uint8_t *p) {
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static uint64_t rd64(const uint8_t *p) { return (uint64_t)rd32(p) | ((uint64_t)rd32(p + 4) << 32); }

static float rdf(const uint8_t *p) {
    acb_f32_bits b;
    b.u = rd32(p);
    return b.f;
}

static void wr16(uint8_t *p, uint16_t v) {
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}

static void wr32(uint8_t *p, uint32_t v) {
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}

static void wr64(uint8_t *p, uint64_t v) {
    wr32(p, (uint32_t)v);
    wr32(p + 4, (uint32_t)(v >> 32));
}

static void wrf(uint8_t *p, float v) {
    acb_f32_bits b;
    b.f = v;
    wr32(p, b.u);
}

static size_t payload_size(uint8_t type) {
    switch (type) {
        case ACB_MSG_POSE: return ACB_POSE_PAYLOAD;
        case ACB_MSG_STATUS: return ACB_STATUS_PAYLOAD;
        case ACB_MSG_COMMAND: return ACB_COMMAND_PAYLOAD;
        case ACB_MSG_ACK: return ACB_ACK_PAYLOAD;
        default: return 0;
    }
}

/* ---- encoder ---- */

static void write_payload(const acb_message_t *m, uint8_t *p) {
    size_t i;
    switch (m->type) {
        case ACB_MSG_POSE:
            wr64(p, m->u.pose.timestamp_us);
            wr32(p + 8, m->u.pose.frame_id);
            for (i = 0; i < 3; i++) wrf(p + 12 + 4 * i, m->u.pose.position[i]);
            for (i = 0; i < 4; i++) wrf(p + 24 + 4 * i, m->u.pose.quat_wxyz[i]);
            wr16(p + 40, m->u.pose.inliers);
            p[42] = m->u.pose.state;
            p[43] = 0;
            wrf(p + 44, m->u.pose.quality);
            break;
        case ACB_MSG_STATUS:
            wr64(p, m->u.status.timestamp_us);
            wrf(p + 8, m->u.status.fps);
            wrf(p + 12, m->u.status.latency_ms);
            wr32(p + 16, m->u.status.frames_dropped);
            wr32(p + 20, m->u.status.poses_dropped);
            p[24] = m->u.status.state;
            p[25] = p[26] = p[27] = 0;
            break;
        case ACB_MSG_COMMAND:
            p[0] = m->u.command.command;
            p[1] = p[2] = p[3] = 0;
            wrf(p + 4, m->u.command.value);
            break;
        default: /* ACB_MSG_ACK */
            wr16(p, m->u.ack.acked_seq);
            p[2] = m->u.ack.command;
            p[3] = m->u.ack.result;
            break;
    }
}

size_t acb_encode(const acb_message_t *msg, uint8_t *out, size_t out_cap) {
    uint8_t body[ACB_LARGEST_BODY];
    size_t plen = payload_size(msg->type);
    size_t blen = ACB_HEADER_SIZE + plen + ACB_CRC_SIZE;
    size_t i, code_at = 0, o = 1;
    uint8_t code = 1;
    if (plen == 0 || out_cap < blen + 2) return 0; /* bodies < 254 bytes: one COBS byte + delimiter */
    body[0] = (uint8_t)ACB_PROTOCOL_VERSION;
    body[1] = msg->type;
    wr16(body + 2, msg->seq);
    body[4] = (uint8_t)plen;
    write_payload(msg, body + ACB_HEADER_SIZE);
    wr32(body + ACB_HEADER_SIZE + plen, acb_crc32(0, body, ACB_HEADER_SIZE + plen));
    for (i = 0; i < blen; i++) {
        if (body[i] == 0) {
            out[code_at] = code;
            code_at = o++;
            code = 1;
        } else {
            out[o++] = body[i];
            if (++code == 0xFF) {
                out[code_at] = code;
                code_at = o++;
                code = 1;
            }
        }
    }
    out[code_at] = code;
    out[o++] = 0;
    return o;
}

/* ---- decoder ---- */

void acb_decoder_init(acb_decoder_t *d) {
    size_t i;
    d->len = 0;
    d->block_code = 0;
    d->block_left = 0;
    d->overflow = 0;
    d->last_reject = ACB_REJECT_COUNT;
    d->frames_ok = 0;
    for (i = 0; i < ACB_REJECT_COUNT; i++) d->rejected[i] = 0;
}

static void append(acb_decoder_t *d, uint8_t byte) {
    if (d->len >= ACB_MAX_BODY) {
        d->overflow = 1;
        return;
    }
    d->body[d->len++] = byte;
}

/* Checks of a complete COBS-decoded body; fills *out and returns ACB_REJECT_COUNT when valid. */
static acb_reject_t parse(const uint8_t *b, size_t len, acb_message_t *out) {
    const uint8_t *p = b + ACB_HEADER_SIZE;
    size_t plen;
    size_t i;
    if (len < ACB_HEADER_SIZE + ACB_CRC_SIZE) return ACB_REJECT_SHORT;
    if (acb_crc32(0, b, len - ACB_CRC_SIZE) != rd32(b + len - ACB_CRC_SIZE)) return ACB_REJECT_CRC;
    if (b[0] != ACB_PROTOCOL_VERSION) return ACB_REJECT_VERSION;
    plen = payload_size(b[1]);
    if (plen == 0) return ACB_REJECT_TYPE;
    if ((size_t)b[4] != len - ACB_HEADER_SIZE - ACB_CRC_SIZE || (size_t)b[4] != plen) return ACB_REJECT_LENGTH;
    out->type = b[1];
    out->seq = rd16(b + 2);
    switch (b[1]) {
        case ACB_MSG_POSE:
            if (p[42] > ACB_TRACKING_OK) return ACB_REJECT_VALUE;
            out->u.pose.timestamp_us = rd64(p);
            out->u.pose.frame_id = rd32(p + 8);
            for (i = 0; i < 3; i++) out->u.pose.position[i] = rdf(p + 12 + 4 * i);
            for (i = 0; i < 4; i++) out->u.pose.quat_wxyz[i] = rdf(p + 24 + 4 * i);
            out->u.pose.inliers = rd16(p + 40);
            out->u.pose.state = p[42];
            out->u.pose.quality = rdf(p + 44);
            break;
        case ACB_MSG_STATUS:
            if (p[24] > ACB_RUNTIME_ERROR) return ACB_REJECT_VALUE;
            out->u.status.timestamp_us = rd64(p);
            out->u.status.fps = rdf(p + 8);
            out->u.status.latency_ms = rdf(p + 12);
            out->u.status.frames_dropped = rd32(p + 16);
            out->u.status.poses_dropped = rd32(p + 20);
            out->u.status.state = p[24];
            break;
        case ACB_MSG_COMMAND:
            out->u.command.command = p[0];
            out->u.command.value = rdf(p + 4);
            break;
        default: /* ACB_MSG_ACK */
            if (p[3] > ACB_ACK_UNSUPPORTED) return ACB_REJECT_VALUE;
            out->u.ack.acked_seq = rd16(p);
            out->u.ack.command = p[2];
            out->u.ack.result = p[3];
            break;
    }
    return ACB_REJECT_COUNT;
}

acb_feed_result_t acb_decoder_feed(acb_decoder_t *d, uint8_t byte, acb_message_t *out) {
    acb_reject_t why;
    if (byte != 0) {
        if (d->overflow) return ACB_NONE; /* skip to the next delimiter */
        if (d->block_left == 0) {
            /* a code byte: the block before it, unless it was a full 254-byte run, ended with a zero */
            if (d->block_code != 0 && d->block_code != 0xFF) append(d, 0);
            d->block_code = byte;
            d->block_left = (uint8_t)(byte - 1);
        } else {
            append(d, byte);
            d->block_left--;
        }
        return ACB_NONE;
    }
    if (d->block_code == 0) return ACB_NONE; /* empty frame: back-to-back delimiters */
    if (d->overflow) {
        why = ACB_REJECT_OVERFLOW;
    } else if (d->block_left != 0) {
        why = ACB_REJECT_COBS;
    } else {
        why = parse(d->body, d->len, out);
    }
    d->len = 0;
    d->block_code = 0;
    d->block_left = 0;
    d->overflow = 0;
    if (why == ACB_REJECT_COUNT) {
        d->frames_ok++;
        return ACB_MESSAGE;
    }
    d->rejected[why]++;
    d->last_reject = why;
    return ACB_REJECTED;
}
