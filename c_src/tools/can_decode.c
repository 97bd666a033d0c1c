/*
 * ddyn_can_decode: decode a candump log (stdin) with the C side of the drive-by-wire protocol
 * (ddyn_dbw_decode over the cantools-generated packers), one output line per input frame:
 *   <ID hex> <result> [<frame> <counter> <name>=<value> ...]
 * result: ok, foreign_id, unknown_id, bad_length, checksum, range, unparsed. The Python tools
 * decode the same logs with cantools (train/data/can_protocol.py); tests/python/test_can_tools.py
 * compares the two line by line.
 */
#include <ctype.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "ddyn/dbw.h"

static const char *result_name(ddyn_dbw_decode_result r)
{
    switch (r) {
    case DDYN_DBW_DECODE_OK: return "ok";
    case DDYN_DBW_DECODE_UNKNOWN_ID: return "unknown_id";
    case DDYN_DBW_DECODE_FOREIGN_ID: return "foreign_id";
    case DDYN_DBW_DECODE_BAD_LENGTH: return "bad_length";
    case DDYN_DBW_DECODE_CHECKSUM: return "checksum";
    case DDYN_DBW_DECODE_RANGE: return "range";
    case DDYN_DBW_DECODE_AUTHENTICATOR: return "authenticator";
    default: return "argument";
    }
}

static int hexval(int c)
{
    return isdigit(c) ? c - '0' : (c >= 'A' && c <= 'F') ? c - 'A' + 10 : (c >= 'a' && c <= 'f') ? c - 'a' + 10 : -1;
}

static void print_values(ddyn_dbw_frame f, const ddyn_dbw_signals *s)
{
    switch (f) {
    case DDYN_DBW_FRAME_COMMAND:
        printf(" Throttle=%.17g Brake=%.17g SteeringAngle=%.17g Enable=%d Mode=%d", s->command.throttle,
               s->command.brake, s->command.steering, s->command.enable ? 1 : 0, (int)s->command.mode);
        break;
    case DDYN_DBW_FRAME_STEERING:
        printf(" SteeringAngle=%.17g SteeringRate=%.17g", s->feedback.steering, s->feedback.steering_rate);
        break;
    case DDYN_DBW_FRAME_STATUS:
        printf(" ThrottlePedal=%.17g BrakePedal=%.17g Mode=%d Enabled=%d DriverOverride=%d Faults=%d",
               s->feedback.throttle_pedal, s->feedback.brake_pedal, (int)s->feedback.mode,
               s->feedback.enabled ? 1 : 0, s->feedback.driver_override ? 1 : 0, (int)s->feedback.faults);
        break;
    case DDYN_DBW_FRAME_WHEEL_SPEEDS:
        printf(" WheelSpeedFront=%.17g WheelSpeedRear=%.17g", s->feedback.wheel_speed_front,
               s->feedback.wheel_speed_rear);
        break;
    case DDYN_DBW_FRAME_IMU:
        printf(" YawRate=%.17g AccelX=%.17g AccelY=%.17g", s->sensors.yaw_rate, s->sensors.accel_x, s->sensors.accel_y);
        break;
    case DDYN_DBW_FRAME_GNSS_POSITION:
        printf(" PositionX=%.17g PositionY=%.17g", s->sensors.gnss_x, s->sensors.gnss_y);
        break;
    case DDYN_DBW_FRAME_GNSS_HEADING:
        printf(" Heading=%.17g FixType=%d", s->sensors.heading, (int)s->sensors.fix_type);
        break;
    default: break;
    }
}

int main(void)
{
    char line[512];
    unsigned long lines = 0;
    while (fgets(line, sizeof(line), stdin) != NULL && lines < 100000000ul) {
        const char *p = strchr(line, ')');
        char *hash;
        unsigned long id;
        uint8_t data[64];
        size_t len = 0;
        ddyn_dbw_signals s;
        ddyn_dbw_frame f = DDYN_DBW_FRAME_COUNT;
        uint8_t counter = 0;
        ddyn_dbw_decode_result r;
        ++lines;
        if (p == NULL) {
            continue;
        }
        /* "(ts) iface ID#DATA [R|T]" */
        p = strchr(p + 2, ' ');
        if (p == NULL) {
            printf("? unparsed\n");
            continue;
        }
        id = strtoul(p + 1, &hash, 16);
        if (*hash != '#') {
            printf("? unparsed\n");
            continue;
        }
        ++hash;
        while (len < sizeof(data) && hexval(hash[0]) >= 0 && hexval(hash[1]) >= 0) {
            data[len++] = (uint8_t)(hexval(hash[0]) * 16 + hexval(hash[1]));
            hash += 2;
        }
        memset(&s, 0, sizeof(s));
        r = ddyn_dbw_decode((uint32_t)id, data, len, &s, &f, &counter);
        printf("%03lX %s", id, result_name(r));
        if (r == DDYN_DBW_DECODE_OK) {
            printf(" %s %d", ddyn_dbw_frame_name(f), (int)counter);
            print_values(f, &s);
        }
        printf("\n");
    }
    return 0;
}
