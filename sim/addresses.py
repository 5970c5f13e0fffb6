"""Where the emulators listen: an IPv4 loopback address only (the tests' and the hardware notes'
rule), so that no emulator can be reached from, or mistaken for, a device on a network."""
import ipaddress


def loopback(host: str, emulator: str = "emulator") -> str:
    """host as an IPv4 loopback address ("localhost" is 127.0.0.1); any other host ends the
    emulator (SystemExit) with a line naming it."""
    address = "127.0.0.1" if host == "localhost" else host
    try:
        if ipaddress.IPv4Address(address).is_loopback:
            return address
    except ipaddress.AddressValueError:
        pass
    raise SystemExit(f"{emulator}: refusing host {host!r}: the emulator listens on loopback only "
                     "(127.0.0.0/8 or localhost)")
