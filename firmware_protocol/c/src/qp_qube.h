/*
 * The QUBE-Servo 2's 17-byte SPI transaction (Quanser's Arduino sample
 * code for the QUBE-Servo 2): 1 MHz, MSB first, SPI mode 2, full duplex.
 * Big-endian fields, unlike the host protocol. The Python twin is
 * firmware_protocol/qube_spi.py.
 */
#ifndef QP_QUBE_H
#define QP_QUBE_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define QP_SPI_SIZE 17u
#define QP_SPI_MODE_BYTE 1u
#define QP_MASK_MOTOR 0x03u
#define QP_MASK_LED 0x1Cu
#define QP_MASK_ENCODER0 0x20u
#define QP_MASK_ENCODER1 0x40u
#define QP_MASK_NORMAL (QP_MASK_MOTOR | QP_MASK_LED)
#define QP_MOTOR_ENABLE 0x8000u
/* Quanser scales volts by 625/15 PWM counts: 24 mV per count. */
#define QP_MILLIVOLTS_PER_PWM 24

typedef struct {
    uint8_t write_mask;
    uint16_t led_red, led_green, led_blue;
    int32_t encoder0_preset, encoder1_preset; /* 24-bit signed */
    uint16_t motor;
} qp_spi_command;

typedef struct {
    uint16_t module_id;
    int32_t encoder0, encoder1; /* sign-extended from 24 bits */
    uint32_t tach_raw;          /* raw 24-bit word */
    uint8_t status;
    uint16_t current_raw;
} qp_spi_response;

/* The 17 bytes the bridge sends (mode 1, a zero, then the fields). */
void qp_spi_pack_command(const qp_spi_command *cmd, uint8_t out[QP_SPI_SIZE]);
/* Read the 17 bytes the QUBE returned. */
void qp_spi_unpack_response(const uint8_t in[QP_SPI_SIZE], qp_spi_response *resp);
/* millivolts / 24 rounded half away from zero, after clamping to +-15000. */
int16_t qp_motor_pwm(int32_t millivolts);
/* Enable bit 15 and 15-bit two's complement PWM; 0 when disabled. */
uint16_t qp_motor_word(int32_t millivolts, int enable);

#ifdef __cplusplus
}
#endif

#endif /* QP_QUBE_H */
