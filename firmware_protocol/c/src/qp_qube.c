/* The QUBE-Servo 2 SPI transaction (see qp_qube.h). */
#include "qp_qube.h"

#include "qp_protocol.h"

static void put_be16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v >> 8);
    p[1] = (uint8_t)(v & 0xFFu);
}

static void put_be24(uint8_t *p, int32_t v)
{
    uint32_t u = (uint32_t)v & 0xFFFFFFUL; /* two's complement, cut to 24 bits */
    p[0] = (uint8_t)(u >> 16);
    p[1] = (uint8_t)((u >> 8) & 0xFFu);
    p[2] = (uint8_t)(u & 0xFFu);
}

static uint32_t get_be24(const uint8_t *p)
{
    return ((uint32_t)p[0] << 16) | ((uint32_t)p[1] << 8) | (uint32_t)p[2];
}

static int32_t sign24(uint32_t u)
{
    /* Portable sign extension: no shift of a negative value, no
     * implementation-defined conversion of an out-of-range unsigned. */
    return (int32_t)((u ^ 0x800000UL) & 0xFFFFFFUL) - (int32_t)0x800000L;
}

void qp_spi_pack_command(const qp_spi_command *cmd, uint8_t out[QP_SPI_SIZE])
{
    out[0] = QP_SPI_MODE_BYTE;
    out[1] = 0;
    out[2] = cmd->write_mask;
    put_be16(out + 3, cmd->led_red);
    put_be16(out + 5, cmd->led_green);
    put_be16(out + 7, cmd->led_blue);
    put_be24(out + 9, cmd->encoder0_preset);
    put_be24(out + 12, cmd->encoder1_preset);
    put_be16(out + 15, cmd->motor);
}

void qp_spi_unpack_response(const uint8_t in[QP_SPI_SIZE], qp_spi_response *resp)
{
    resp->module_id = (uint16_t)(((uint16_t)in[0] << 8) | in[1]);
    resp->encoder0 = sign24(get_be24(in + 2));
    resp->encoder1 = sign24(get_be24(in + 5));
    resp->tach_raw = get_be24(in + 8);
    resp->status = in[11];
    resp->current_raw = (uint16_t)(((uint16_t)in[12] << 8) | in[13]);
}

int16_t qp_motor_pwm(int32_t millivolts)
{
    int32_t mv = millivolts, pwm;
    if (mv > QP_MAX_MILLIVOLTS) {
        mv = QP_MAX_MILLIVOLTS;
    } else if (mv < -QP_MAX_MILLIVOLTS) {
        mv = -QP_MAX_MILLIVOLTS;
    }
    /* C division truncates toward zero; round half away from zero by hand. */
    /* |mv| + 12 <= 15012 fits 16 bits: a 16-bit division, a third of the
     * cycles of a 32-bit one on an 8-bit AVR, same result. */
    pwm = (uint16_t)((uint16_t)(mv < 0 ? -mv : mv) + QP_MILLIVOLTS_PER_PWM / 2) / (uint16_t)QP_MILLIVOLTS_PER_PWM;
    return (int16_t)(mv < 0 ? -pwm : pwm);
}

uint16_t qp_motor_word(int32_t millivolts, int enable)
{
    if (!enable) {
        return 0;
    }
    return (uint16_t)(QP_MOTOR_ENABLE | ((uint16_t)qp_motor_pwm(millivolts) & 0x7FFFu));
}
