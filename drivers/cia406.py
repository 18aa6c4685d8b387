"""The CiA 406 (encoder profile) object dictionary used by the encoder nodes.

The EDS below is the "vendor file" of the emulated encoders: the master (the driver)
and the emulated slaves both load it, as a real master loads the vendor's EDS.
Objects: 0x1000 device type (0x00020196: CiA 406, multi-turn rotary encoder), 0x1001
error register, 0x1017 producer heartbeat time (ms), 0x1018 identity, 0x1800/0x1A00
TPDO1 (COB-ID 0x180 + node id, transmission type 1 = every SYNC, mapping 0x6004:00 u32),
0x6001 measuring units per revolution, 0x6002 total measuring range, 0x6004 position
value (counts, u32).
"""

from __future__ import annotations

import io

import canopen

DEVICE_TYPE_CIA406_MULTITURN = 0x00020196
POSITION_INDEX = 0x6004
TPDO1_COMM = 0x1800
TPDO1_MAP = 0x1A00
HEARTBEAT_INDEX = 0x1017

_VAR = """[{index}]
ParameterName={name}
ObjectType=0x7
DataType={dtype}
AccessType={access}
DefaultValue={default}
PDOMapping={pdo}
"""

_SUB = """[{index}sub{sub}]
ParameterName={name}
ObjectType=0x7
DataType={dtype}
AccessType={access}
DefaultValue={default}
PDOMapping=0
"""

_REC = """[{index}]
ParameterName={name}
ObjectType=0x9
SubNumber={n}
"""

U8, U16, U32 = "0x0005", "0x0006", "0x0007"


def eds_text(counts_per_rev: int = 131072, turns: int = 4096) -> str:
    """The EDS of an encoder with ``counts_per_rev`` single-turn and ``turns`` multi-turn.

    Long because it is the file's text: one entry per object, in the file's order."""
    parts = [
        "[FileInfo]\nFileName=cia406_encoder.eds\nFileVersion=1\nDescription=CiA 406 encoder\n",
        "[DeviceInfo]\nVendorName=grating-twin emulator\nProductName=MT encoder\n"
        "BaudRate_1000=1\nNrOfRXPDO=0\nNrOfTXPDO=1\n",
        "[MandatoryObjects]\nSupportedObjects=3\n1=0x1000\n2=0x1001\n3=0x1018\n",
        "[OptionalObjects]\nSupportedObjects=4\n1=0x1017\n2=0x1800\n3=0x1A00\n4=0x6004\n",
        "[ManufacturerObjects]\nSupportedObjects=0\n",
        _VAR.format(
            index="1000",
            name="Device type",
            dtype=U32,
            access="ro",
            default=hex(DEVICE_TYPE_CIA406_MULTITURN),
            pdo=0,
        ),
        _VAR.format(index="1001", name="Error register", dtype=U8, access="ro", default=0, pdo=0),
        _VAR.format(
            index="1017", name="Producer heartbeat time", dtype=U16, access="rw", default=100, pdo=0
        ),
        _REC.format(index="1018", name="Identity object", n=5),
        _SUB.format(
            index="1018", sub=0, name="Highest sub-index", dtype=U8, access="ro", default=4
        ),
        _SUB.format(index="1018", sub=1, name="Vendor-ID", dtype=U32, access="ro", default=0x5A5A),
        _SUB.format(index="1018", sub=2, name="Product code", dtype=U32, access="ro", default=406),
        _SUB.format(index="1018", sub=3, name="Revision number", dtype=U32, access="ro", default=1),
        _SUB.format(index="1018", sub=4, name="Serial number", dtype=U32, access="ro", default=0),
        _REC.format(index="1800", name="TPDO1 communication parameter", n=3),
        _SUB.format(
            index="1800", sub=0, name="Highest sub-index", dtype=U8, access="ro", default=2
        ),
        _SUB.format(
            index="1800", sub=1, name="COB-ID", dtype=U32, access="rw", default="$NODEID+0x180"
        ),
        _SUB.format(
            index="1800", sub=2, name="Transmission type", dtype=U8, access="rw", default=1
        ),
        _REC.format(index="1A00", name="TPDO1 mapping parameter", n=2),
        _SUB.format(
            index="1A00", sub=0, name="Number of entries", dtype=U8, access="rw", default=1
        ),
        _SUB.format(
            index="1A00",
            sub=1,
            name="Mapping entry 1",
            dtype=U32,
            access="rw",
            default="0x60040020",
        ),
        _VAR.format(
            index="6001",
            name="Measuring units per revolution",
            dtype=U32,
            access="ro",
            default=counts_per_rev,
            pdo=0,
        ),
        _VAR.format(
            index="6002",
            name="Total measuring range",
            dtype=U32,
            access="ro",
            default=counts_per_rev * turns,
            pdo=0,
        ),
        _VAR.format(index="6004", name="Position value", dtype=U32, access="ro", default=0, pdo=1),
    ]
    text = "\n".join(parts)
    # 0x6001/0x6002 are listed as optional objects too
    return text.replace(
        "SupportedObjects=4\n1=0x1017\n2=0x1800\n3=0x1A00\n4=0x6004\n",
        "SupportedObjects=6\n1=0x1017\n2=0x1800\n3=0x1A00\n4=0x6001\n5=0x6002\n6=0x6004\n",
    )


def object_dictionary(
    node_id: int, counts_per_rev: int = 131072, turns: int = 4096
) -> canopen.ObjectDictionary:
    """The parsed object dictionary for ``node_id``."""
    f = io.StringIO(eds_text(counts_per_rev, turns))
    f.name = "cia406_encoder.eds"
    return canopen.import_od(f, node_id)
