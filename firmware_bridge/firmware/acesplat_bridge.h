/*
 * acesplat firmware bridge, protocol v1: the microcontroller side (see ../PROTOCOL.md).
 *
 * C99, no dynamic memory, no libc calls beyond what the compiler emits for struct copies.
 * The decoder is fed one byte at a time (e.g. from a UART RX interrupt or a DMA ring buffer)
 * and needs sizeof(acb_decoder_t) bytes of RAM (about 300). Floats are IEEE-754 binary32.
 *
 * Typical use:
 *
 *     static acb_decoder_t dec;
 *     acb_decoder_init(&dec);
 *     ...
 *     acb_message_t msg;
 *     if (acb_decoder_feed(&dec, byte, &msg) == ACB_MESSAGE && msg.type == ACB_MSG_POSE) { use(msg.u.pose); }
 *
 *     uint8_t wire[ACB_MAX_WIRE];
 *     acb_message_t cmd = {0};
 *     cmd.type = ACB_MSG_COMMAND; cmd.seq = my_seq++; cmd.u.command.command = ACB_CMD_SET_RATE; cmd.u.command.value = 30.0f;
 *     uart_write(wire, acb_encode(&cmd, wire, sizeof wire));
 */
#ifndef ACESPLAT_BRIDGE_H
#define ACESPLAT_BRIDGE_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define ACB_PROTOCOL_VERSION 1u
#define ACB_HEADER_SIZE 5u
#define ACB_CRC_SIZE 4u
#define ACB_MAX_BODY 254u  /* header + payload + CRC; longer frames are rejected as overflow */
#define ACB_MAX_WIRE 257u  /* COBS of a ACB_MAX_BODY body (256) plus the 0x00 delimiter */

#define ACB_POSE_PAYLOAD 48u
#define ACB_STATUS_PAYLOAD 28u
#define ACB_COMMAND_PAYLOAD 8u
#define ACB_ACK_PAYLOAD 4u

enum acb_msg_type { ACB_MSG_POSE = 0x01, ACB_MSG_STATUS = 0x02, ACB_MSG_COMMAND = 0x10, ACB_MSG_ACK = 0x11 };
enum acb_tracking { ACB_TRACKING_LOST = 0, ACB_TRACKING_OK = 1 };
enum acb_runtime_state {
    ACB_RUNTIME_STARTING = 0, ACB_RUNTIME_TRACKING = 1, ACB_RUNTIME_LOST = 2, ACB_RUNTIME_PAUSED = 3, ACB_RUNTIME_ERROR = 4
};
enum acb_command_code { ACB_CMD_RELOCALIZE = 1, ACB_CMD_PAUSE = 2, ACB_CMD_RESUME = 3, ACB_CMD_SET_RATE = 4 };
enum acb_ack_result { ACB_ACK_ACCEPTED = 0, ACB_ACK_REJECTED = 1, ACB_ACK_UNSUPPORTED = 2 };

/* Camera-to-world pose in the map frame, OpenCV camera axes (x right, y down, z forward), metres. */
typedef struct {
    uint64_t timestamp_us;  /* capture time, host clock */
    uint32_t frame_id;
    float position[3];      /* camera centre in the map */
    float quat_wxyz[4];     /* rotation camera -> map, Hamilton, w >= 0 */
    uint16_t inliers;
    uint8_t state;          /* enum acb_tracking */
    float quality;          /* 0..1 */
} acb_pose_t;

typedef struct {
    uint64_t timestamp_us;
    float fps;
    float latency_ms;
    uint32_t frames_dropped;
    uint32_t poses_dropped;
    uint8_t state;          /* enum acb_runtime_state */
} acb_status_t;

typedef struct {
    uint8_t command;        /* enum acb_command_code (unknown codes are valid frames; the host ACKs UNSUPPORTED) */
    float value;            /* SET_RATE: Hz; otherwise 0 */
} acb_command_t;

typedef struct {
    uint16_t acked_seq;     /* sequence number of the COMMAND frame */
    uint8_t command;
    uint8_t result;         /* enum acb_ack_result */
} acb_ack_t;

typedef struct {
    uint8_t type;           /* enum acb_msg_type */
    uint16_t seq;
    union {
        acb_pose_t pose;
        acb_status_t status;
        acb_command_t command;
        acb_ack_t ack;
    } u;
} acb_message_t;

/* Why a frame was rejected, in the order the checks run (same order as the Python decoder). */
typedef enum {
    ACB_REJECT_OVERFLOW = 0,  /* decoded body longer than ACB_MAX_BODY */
    ACB_REJECT_COBS,          /* last COBS block truncated by the delimiter */
    ACB_REJECT_SHORT,         /* body shorter than header + CRC */
    ACB_REJECT_CRC,
    ACB_REJECT_VERSION,
    ACB_REJECT_TYPE,
    ACB_REJECT_LENGTH,        /* payload length differs from the header or from the type's layout */
    ACB_REJECT_VALUE,         /* enum field out of range (tracking state, runtime state, ack result) */
    ACB_REJECT_COUNT
} acb_reject_t;

typedef enum { ACB_NONE = 0, ACB_MESSAGE = 1, ACB_REJECTED = 2 } acb_feed_result_t;

typedef struct {
    uint8_t body[ACB_MAX_BODY];
    uint16_t len;             /* decoded bytes so far */
    uint8_t block_code;       /* code byte of the current COBS block; 0 = nothing since the last delimiter */
    uint8_t block_left;       /* data bytes still expected in the current block */
    uint8_t overflow;
    acb_reject_t last_reject;
    uint32_t frames_ok;
    uint32_t rejected[ACB_REJECT_COUNT];
} acb_decoder_t;

void acb_decoder_init(acb_decoder_t *d);

/* Feed one received byte. Returns ACB_MESSAGE when a valid frame ended (written to *out),
 * ACB_REJECTED when a frame ended and was rejected (reason in d->last_reject), ACB_NONE otherwise. */
acb_feed_result_t acb_decoder_feed(acb_decoder_t *d, uint8_t byte, acb_message_t *out);

/* Encode msg (type, seq and the matching union member) as a complete frame including the 0x00
 * delimiter. Returns the number of bytes written, or 0 for an unknown type or a too small buffer
 * (ACB_MAX_WIRE always suffices). */
size_t acb_encode(const acb_message_t *msg, uint8_t *out, size_t out_cap);

/* CRC-32 (IEEE 802.3, reflected 0xEDB88320, init and final xor 0xFFFFFFFF); chain with crc = 0 initially. */
uint32_t acb_crc32(uint32_t crc, const uint8_t *data, size_t len);

#ifdef __cplusplus
}
#endif

#endif /* ACESPLAT_BRIDGE_H */
