"""A minimal ``machine`` stand-in for running tacfoot's MicroPython code in tests.

It runs on real MicroPython (the WebAssembly port under Node, see run.mjs) and on
CPython. Only the last inch of hardware is replaced: the code under test calls
these classes exactly as it calls the real ``machine`` module on an RP2040, and
the test drives the other side (the pin levels, the ADC reading, the I2C device,
the bytes arriving on the UART) through the class-level hooks documented below.

Sections are kept separate so each peripheral can grow on its own.
"""

try:
    import time as _time
    _ticks_ms = _time.ticks_ms
except AttributeError:          # CPython
    import time as _time

    def _ticks_ms():
        return int(_time.monotonic() * 1000) & 0x3FFFFFFF


class MachineReset(Exception):
    """Raised by reset() and by an expired WDT (the chip would reboot)."""


def reset():
    raise MachineReset("machine.reset()")


def freq(hz=None):
    return 125000000


def unique_id():
    return b"\x74\x61\x63\x66\x6f\x6f\x74\x00"


def disable_irq():
    return 0


def enable_irq(state=0):
    pass


# -- Pin ---------------------------------------------------------------------------
class Pin:
    IN = 0
    OUT = 1
    OPEN_DRAIN = 2
    PULL_UP = 1
    PULL_DOWN = 2
    IRQ_FALLING = 4
    IRQ_RISING = 8

    #: test hook: pin id -> level that an input pin reads (default 0, or 1 with PULL_UP)
    levels = {}
    #: test hook: pin id -> number of rising edges written to an output pin
    rising = {}

    def __init__(self, id, mode=-1, pull=-1, value=None):
        self.id = id
        self.mode = mode
        self.pull = pull
        self._out = 0
        self._irq = None
        if value is not None:
            self.value(value)

    def init(self, mode=-1, pull=-1, value=None):
        self.__init__(self.id, mode, pull, value)

    def value(self, v=None):
        if v is None:
            if self.mode == Pin.OUT:
                return self._out
            return Pin.levels.get(self.id, 1 if self.pull == Pin.PULL_UP else 0)
        v = 1 if v else 0
        if v and not self._out:
            Pin.rising[self.id] = Pin.rising.get(self.id, 0) + 1
        self._out = v

    def __call__(self, v=None):
        return self.value(v)

    def on(self):
        self.value(1)

    def off(self):
        self.value(0)

    def high(self):
        self.value(1)

    def low(self):
        self.value(0)

    def irq(self, handler=None, trigger=IRQ_FALLING | IRQ_RISING):
        self._irq = handler
        return None


# -- PWM ---------------------------------------------------------------------------
class PWM:
    def __init__(self, pin, freq=1000, duty_u16=0):
        self.pin = pin
        self._freq = freq
        self._duty = duty_u16
        self.active = True

    def freq(self, f=None):
        if f is None:
            return self._freq
        self._freq = f

    def duty_u16(self, d=None):
        if d is None:
            return self._duty
        self._duty = max(0, min(65535, int(d)))

    def deinit(self):
        self.active = False
        self._duty = 0


# -- ADC ---------------------------------------------------------------------------
class ADC:
    #: test hook: pin/channel id -> 16-bit reading, or a callable returning one
    values = {}

    def __init__(self, pin):
        self.id = pin.id if isinstance(pin, Pin) else pin

    def read_u16(self):
        v = ADC.values.get(self.id, 0)
        if callable(v):
            v = v()
        return max(0, min(65535, int(v)))


# -- I2C ---------------------------------------------------------------------------
class I2C:
    """Register-level I2C. A test attaches a device object to an address:
    ``I2C.devices[0x68] = dev`` where ``dev.read(reg, n) -> bytes`` and
    ``dev.write(reg, data)``; either may raise OSError. A transaction to an empty
    address raises OSError(19) (ENODEV), as on an RP2040."""

    #: test hook: 7-bit address -> device object
    devices = {}

    def __init__(self, id=0, scl=None, sda=None, freq=400000, timeout=50000):
        self.id = id
        self.freq = freq

    def _dev(self, addr):
        d = I2C.devices.get(addr)
        if d is None:
            raise OSError(19)
        return d

    def scan(self):
        return sorted(I2C.devices.keys())

    def readfrom_mem_into(self, addr, memaddr, buf, addrsize=8):
        data = self._dev(addr).read(memaddr, len(buf))
        for i in range(len(buf)):
            buf[i] = data[i]

    def readfrom_mem(self, addr, memaddr, nbytes, addrsize=8):
        return bytes(self._dev(addr).read(memaddr, nbytes))

    def writeto_mem(self, addr, memaddr, buf, addrsize=8):
        self._dev(addr).write(memaddr, bytes(buf))


# -- UART --------------------------------------------------------------------------
class UART:
    """A UART whose far end is the test: ``feed(data)`` queues bytes to be read
    (up to ``rxbuf``; beyond that they are lost, as in a full ring buffer, and
    counted in ``overrun``), and ``take()`` returns and clears what was written.
    ``tx_limit`` (None: no limit) caps how many bytes one write() accepts."""

    def __init__(self, id=0, baudrate=115200, bits=8, parity=None, stop=1, tx=None, rx=None,
                 timeout=0, rxbuf=256, txbuf=256):
        self.id = id
        self.baudrate = baudrate
        self.rxbuf = rxbuf
        self._rx = bytearray()
        self._tx = bytearray()
        self.overrun = 0
        self.tx_limit = None

    def init(self, baudrate=115200, **kw):
        self.baudrate = baudrate

    # the test's side
    def feed(self, data):
        room = self.rxbuf - len(self._rx)
        if room < len(data):
            self.overrun += len(data) - max(room, 0)
            data = data[:max(room, 0)]
        self._rx.extend(data)

    def take(self):
        out = bytes(self._tx)
        self._tx = bytearray()
        return out

    # the code under test's side
    def any(self):
        return len(self._rx)

    def read(self, nbytes=None):
        if not self._rx:
            return None
        n = len(self._rx) if nbytes is None else min(nbytes, len(self._rx))
        out = bytes(self._rx[:n])
        self._rx = self._rx[n:]
        return out

    def readinto(self, buf, nbytes=None):
        if not self._rx:
            return None
        n = len(buf) if nbytes is None else min(nbytes, len(buf))
        n = min(n, len(self._rx))
        for i in range(n):
            buf[i] = self._rx[i]
        self._rx = self._rx[n:]
        return n

    def write(self, buf):
        n = len(buf) if self.tx_limit is None else min(len(buf), self.tx_limit)
        self._tx.extend(bytes(buf[:n]))
        return n

    def flush(self):
        pass

    def txdone(self):
        return True


# -- WDT ---------------------------------------------------------------------------
class WDT:
    """``machine.WDT``: once started it cannot be stopped. ``check()`` (the test
    calls it, standing in for the hardware counter) raises MachineReset if more than
    ``timeout`` ms passed since the last feed(). ``WDT.started`` counts starts."""

    started = 0

    def __init__(self, id=0, timeout=5000):
        self.timeout = timeout
        self.last = _ticks_ms()
        self.feeds = 0
        WDT.started += 1

    def feed(self):
        self.last = _ticks_ms()
        self.feeds += 1

    def check(self, now_ms=None):
        now = _ticks_ms() if now_ms is None else now_ms
        if (now - self.last) > self.timeout:
            raise MachineReset("WDT expired")


# -- Timer -------------------------------------------------------------------------
class Timer:
    ONE_SHOT = 0
    PERIODIC = 1

    def __init__(self, id=-1, mode=PERIODIC, period=-1, freq=-1, callback=None):
        self.callback = callback

    def init(self, mode=PERIODIC, period=-1, freq=-1, callback=None):
        self.callback = callback

    def deinit(self):
        self.callback = None
