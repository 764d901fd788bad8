// run.mjs IMAGE(.uf2|.bin): the spiel-edge RP2040 image in rp2040js with its USB CDC device
// bridged to stdin/stdout (run-emulated.sh makes that a pty with socat). The chip starts at
// boot2 (0x10000000), as the rp2040js demos do: the ROM's flash boot needs QSPI commands the
// emulator does not model. So no RP2040 bootrom is loaded: the Raspberry Pi B1 ROM image holds
// code (mufplib) licensed for use on RP2040 silicon only or GPLv2, which this project does not
// ship. In its place a ROM of zeros whose vector table gives boot2 the stack the real ROM sets
// up (0x20042000). The firmware calls into the ROM only on paths that run on hardware alone
// (flash erase/program and unique id, reboot to BOOTSEL): docs/build-a-board.md. A watchdog reset (REBOOT, hal_reset) starts a new chip with the
// same flash and watchdog scratch registers, as a real watchdog reset keeps them. Exits when
// stdin closes or its parent goes; diagnostics go to stderr only.
import { readFileSync } from 'node:fs';
import { Simulator, USBCDC, LogLevel } from 'rp2040js';

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

const pending = []; // host -> device bytes not yet taken by the CDC host's 512-byte FIFO
let sim = null, cdc = null, boots = 0;

function pump() {
  while (pending.length && cdc && !cdc.txFIFO.full) cdc.txFIFO.push(pending.shift());
}

function boot(flash, scratch) {
  if (sim) sim.stop();
  sim = new Simulator();
  const mcu = sim.rp2040;
  mcu.logger = quiet;
  mcu.loadBootrom(bootrom); // (this erases the flash array: fill it afterwards)
  if (flash) mcu.flash.set(flash); else loadImage(mcu.flash);
  const watchdog = mcu.peripherals[0x40058];
  if (scratch) watchdog.scratchData.set(scratch);
  watchdog.onWatchdogTrigger = () => {
    const keep = mcu.flash.slice(0), regs = watchdog.scratchData.slice(0);
    setImmediate(() => boot(keep, regs)); // not from inside the running instruction
    sim.stop();
  };
  cdc = new USBCDC(mcu.usbCtrl);
  cdc.onSerialData = (buf) => process.stdout.write(Buffer.from(buf));
  cdc.onDeviceConnected = () => process.stderr.write(
    `rp2040js: USB configured: CDC data IN endpoint ${cdc.inEndpoint}, OUT ${cdc.outEndpoint}\n`);
  const read = mcu.usbCtrl.onEndpointRead;
  mcu.usbCtrl.onEndpointRead = (ep, size) => { pump(); read(ep, size); };
  boots++;
  process.stderr.write(`rp2040js: boot ${boots}\n`);
  mcu.core.PC = 0x10000000;
  sim.execute();
}

process.stdin.on('data', (chunk) => { for (const b of chunk) pending.push(b); pump(); });
process.stdin.on('end', () => process.exit(0));
process.on('SIGTERM', () => process.exit(0));
const parent = process.ppid;
setInterval(() => { if (process.ppid !== parent) process.exit(0); }, 500).unref();
boot(null, null);
