"""Benchmark of Rig.poll() with the machine stand-in (device/sim/mpy/lib/machine.py),
not for the board:

    node device/sim/mpy/run.mjs --lib device/sim/mpy/lib --lib device/micropython device/micropython/rig/bench.py

Prints microseconds per poll idle, moving, and moving while streaming, and the
bytes the link decoder allocates over 1020 bytes (docs/BENCHMARKS.md)."""
import gc, time
from machine import Pin, PWM, ADC, UART
from rig.drivers import Stepper, DCMotor, AdcLoad
from rig.firmware import Rig, put_i32, put_u16, HOME, MOVE_TO, STREAM
from tflink import Encoder
Pin.levels = {14: 1}
uart = UART(0, rxbuf=4096)
rig = Rig(uart, Stepper(Pin(2, Pin.OUT), Pin(3, Pin.OUT), steps_per_mm=100),
          DCMotor(PWM(Pin(6)), Pin(7, Pin.OUT), Pin(8, Pin.OUT)), AdcLoad(ADC(26)), None,
          Pin(14, Pin.IN), None, travel_mm=40, link_timeout_ms=100000)
enc = Encoder(); pl = bytearray(8)
now = 0


def polls(n):
    global now
    t = time.ticks_us()
    for _ in range(n):
        now += 1000
        rig.poll(now)
    return time.ticks_diff(time.ticks_us(), t) / n
print("idle_us_per_poll", polls(2000))
uart.feed(bytes(enc.frame(HOME, 1, 0, pl, 0))); polls(5); uart.take()
Pin.levels = {14: 0}
put_i32(pl, 0, 30000); put_i32(pl, 4, 20000)
uart.feed(bytes(enc.frame(MOVE_TO, 2, 0, pl, 8))); polls(2); uart.take()
print("moving_us_per_poll_2steps", polls(500))
put_u16(pl, 0, 5); uart.feed(bytes(enc.frame(STREAM, 3, 0, pl, 2)))
print("moving_streaming_us_per_poll", polls(500)); uart.take()
put_u16(pl, 0, 0); uart.feed(bytes(enc.frame(STREAM, 4, 0, pl, 2))); polls(3); uart.take()
junk = bytearray(1020)
for i in range(1020): junk[i] = 1 + i % 255
gc.collect(); a0 = gc.mem_alloc()
rig.dec.feed(junk, len(junk))
print("alloc_bytes_decoding_1020_bytes", gc.mem_alloc() - a0)
