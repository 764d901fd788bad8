// run.mjs IMAGE(.uf2|.bin): the spiel-edge RP2040 image in rp2040js with its USB CDC device
// bridged to stdin/stdout (run-emulated.sh makes that a pty with socat). The chip starts at
// boot2 (0x10000000), as the rp2040js demos do: the ROM's flash boot needs QSPI commands the
// emulator does not model. So no RP2040 bootrom is loaded: the Raspberry Pi B1 ROM image holds
// code (mufplib) licensed for use on RP2040 silicon only or GPLv2, which this project does not
// ship. In its place a ROM of zeros whose vector table gives boot2 the stack the real ROM sets
// up (0x20042000). The firmware calls into the ROM only on paths that run on hardware alone
// (flash erase/program and unique id, reboot to BOOTSEL): docs/build-a-board.md.
// A watchdog reset (REBOOT, a trial that stops kicking) starts a new chip with the same flash
// and watchdog scratch registers, as a real watchdog reset keeps them. Exits when stdin closes
// or its parent goes; diagnostics go to stderr only (RP2040_EMU_TRACE=1: every transfer too).
// Power cuts for the tests: RP2040_EMU_CUT_AT=N cuts the power at the first store of the Nth
// flash operation since start (an operation: stores to one 256-byte page; an erase spans 16),
// that store lost; a new chip starts with the flash as it was and the watchdog scratch
// registers cleared, as after a power cycle. RP2040_EMU_FLASH_OPS=1 reports every operation.
import { readFileSync } from 'node:fs';
import { Simulator, USBCDC } from 'rp2040js';

const image = process.argv[2];
if (!image) {
  process.stderr.write('usage: node run.mjs IMAGE.uf2|IMAGE.bin\n');
  process.exit(2);
}
const bootrom = new Uint32Array(4096); // 16 KiB of ROM
bootrom[0] = 0x20042000; // initial SP: the top of SRAM bank 5, where the real ROM puts it
const quiet = {
  debug() {}, info() {}, warn() {},
  error(component, message) { process.stderr.write(`rp2040js [${component}] ${message}\n`); },
};

function loadImage(flash) {
  const data = readFileSync(image);
  if (image.endsWith('.uf2')) {
    for (let off = 0; off + 512 <= data.length; off += 512) {
      const v = new DataView(data.buffer, data.byteOffset + off, 512);
      if (v.getUint32(0, true) !== 0x0a324655 || v.getUint32(4, true) !== 0x9e5d5157) continue;
      const addr = v.getUint32(12, true), size = v.getUint32(16, true);
      flash.set(data.subarray(off + 32, off + 32 + size), addr - 0x10000000);
    }
  } else {
    flash.set(data, 0);
  }
}

const cutAt = Number(process.env.RP2040_EMU_CUT_AT || 0);
const reportOps = Boolean(process.env.RP2040_EMU_FLASH_OPS);
let flashOps = 0, lastPage = -1;

// Count the flash operations of a chip's stores (the emulator build erases and programs flash
// by storing into the XIP window, flash_rp2040.c) and cut the power at the chosen one.
function watchFlash(mcu) {
  if (!cutAt && !reportOps) return;
  const store = mcu.writeUint32.bind(mcu); // writeUint8/16 store through it too
  mcu.writeUint32 = (address, value) => {
    if (address >= 0x10000000 && address < 0x10000000 + mcu.flash.length && sim?.rp2040 === mcu) {
      const page = (address - 0x10000000) >>> 8;
      if (page !== lastPage) {
        lastPage = page;
        flashOps++;
        if (reportOps) process.stderr.write(`rp2040js: flash op ${flashOps} at 0x${(page << 8).toString(16)}\n`);
        if (flashOps === cutAt) {
          process.stderr.write(`rp2040js: power cut at flash op ${flashOps}\n`);
          lastPage = -1;
          restart(mcu.flash.slice(0), null); // this store lost
          return;
        }
      }
    }
    store(address, value);
  };
}

const pending = []; // host -> device bytes the device has not read yet
let sim = null, cdc = null, boots = 0, outWait = null, timer = null, wallStart = 0n;

// The host side of the CDC OUT endpoint as a real host does it: a read the device arms is
// answered when the host has bytes (a real host NAKs until then). rp2040js's own USBCDC answers
// at once with zero bytes, which makes the device take an interrupt every 10 us of emulated time
// and never sleep.
function pump() {
  // no chip between a watchdog reset and the next boot (host bytes can come in between)
  if (sim === null || outWait === null || !pending.length) return;
  const data = Uint8Array.from(pending.splice(0, Math.min(outWait, pending.length)));
  outWait = null;
  sim.rp2040.usbCtrl.endpointReadDone(cdc.outEndpoint, data);
}

// Run the chip. While it sleeps (WFI) its clock moves to its next alarm, or with the wall clock
// when it has none, but never ahead of the wall clock since boot: emulated time is at most real
// time (less while the emulated CPU is busy: it runs slower than the chip) and an idle chip
// costs no host CPU.
function wallNanos() {
  return Number(process.hrtime.bigint() - wallStart);
}
function run(me) {
  timer = null;
  const mcu = me.rp2040, clock = me.clock;
  for (let i = 0; i < 200000 && sim === me; i++) {
    if (mcu.core.waiting && mcu.core.pendingInterrupts & mcu.core.enabledInterrupts) {
      // WFI returns while an enabled interrupt is pending, PRIMASK or not (ARMv6-M); rp2040js
      // 1.4.1 wakes only on a new one, so one that came just before the WFI slept forever
      mcu.core.waiting = false;
    }
    if (mcu.core.waiting) {
      const next = clock.nanosToNextAlarm, room = wallNanos() - clock.nanos;
      if (next > 0 && next <= room) {
        clock.tick(next);
        continue;
      }
      if (room > 0) clock.tick(room);
      const sleep = next > 0 ? (next - room) / 1e6 : 5;
      timer = setTimeout(() => run(me), Math.min(Math.max(sleep, 1), 20));
      return;
    }
    clock.tick(mcu.core.executeInstruction() * 8); // 125 MHz: 8 ns a cycle
  }
  if (sim === me) timer = setImmediate(() => run(me));
}
// Run now (host bytes arrived): one loop only, whatever was scheduled is dropped.
function wake() {
  if (timer !== null) {
    clearTimeout(timer);
    clearImmediate(timer);
  }
  timer = setImmediate(() => run(sim));
}

// A new chip with this flash (and these watchdog scratch registers, or cleared): the running
// loop ends with the current instruction, and that chip's armed OUT read with it.
function restart(flash, scratch) {
  sim = null;
  outWait = null;
  setImmediate(() => boot(flash, scratch));
}

function boot(flash, scratch) {
  sim = new Simulator();
  const mcu = sim.rp2040;
  mcu.logger = quiet;
  mcu.loadBootrom(bootrom); // (this erases the flash array: fill it afterwards)
  if (flash) mcu.flash.set(flash); else loadImage(mcu.flash);
  watchFlash(mcu);
  const watchdog = mcu.peripherals[0x40058];
  if (scratch) watchdog.scratchData.set(scratch);
  watchdog.onWatchdogTrigger = () => {
    // once per chip: rp2040js 1.4.1 re-arms the expired watchdog's alarm 0 ns ahead, which
    // would fire again at the same instant forever; the chip is reset anyway
    watchdog.alarm.enable = false;
    watchdog.timer.enable = false;
    watchdog.onWatchdogTrigger = () => {};
    restart(mcu.flash.slice(0), watchdog.scratchData.slice(0));
  };
  cdc = new USBCDC(mcu.usbCtrl);
  cdc.onSerialData = (buf) => {
    if (trace) trace(`device ${buf.length} B, t ${mcu.clock.nanos}`);
    process.stdout.write(Buffer.from(buf));
  };
  cdc.onDeviceConnected = () => process.stderr.write(
    `rp2040js: USB configured: CDC data IN endpoint ${cdc.inEndpoint}, OUT ${cdc.outEndpoint}\n`);
  const read = mcu.usbCtrl.onEndpointRead;
  outWait = null;
  mcu.usbCtrl.onEndpointRead = (ep, size) => {
    if (ep === cdc.outEndpoint) {
      outWait = size;
      pump();
    } else {
      read(ep, size);
    }
  };
  boots++;
  process.stderr.write(`rp2040js: boot ${boots}\n`);
  mcu.core.PC = 0x10000000;
  wallStart = process.hrtime.bigint();
  wake();
}

const trace = process.env.RP2040_EMU_TRACE ? (text) => process.stderr.write(`${text}\n`) : null;
process.stdin.on('data', (chunk) => {
  if (trace) trace(`host ${chunk.length} B, device reading: ${outWait}, t ${sim && sim.clock.nanos}`);
  for (const b of chunk) pending.push(b);
  pump();
  if (sim) wake();
});
process.stdin.on('end', () => process.exit(0));
process.on('SIGTERM', () => process.exit(0));
if (trace) {
  setInterval(() => sim && trace(`pc ${sim.rp2040.core.PC.toString(16)}, waiting ${sim.rp2040.core.waiting}, t ${sim.clock.nanos}`), 1000).unref();
}
const parent = process.ppid;
setInterval(() => { if (process.ppid !== parent) process.exit(0); }, 500).unref();
boot(null, null);
