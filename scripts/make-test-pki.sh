#!/bin/sh
# make-test-pki.sh: a TEST certificate authority and certificates for a zenoh cell over
# several hosts (docs/deployment.md). Not for production keys: no passphrases, short-lived.
#
#   scripts/make-test-pki.sh DIR [ROUTER_SAN [CN ...]]
#
# DIR         is created (must not exist yet: nothing is overwritten)
# ROUTER_SAN  the router certificate's subjectAltName, i.e. every name or address the
#             daemons and twins connect to (default "DNS:localhost,IP:127.0.0.1"),
#             e.g. "DNS:router.cell1.lan,IP:10.231.0.2"
# CN ...      more client identities, each CN.pem and CN.key (several cells on one
#             router: daemon-cell2 twin-cell2 ..., deploy/router-cells.json5)
#
# Writes (each key beside its certificate, mode 600; PEM; EC P-256):
#   ca.pem                          the cell's CA (root_ca_certificate everywhere)
#   router.pem    router.key        CN router: the router's TLS server certificate
#   daemon.pem    daemon.key        CN daemon: may publish the cell's data keys (cell/<cell>/**)
#   twin.pem      twin.key          CN twin: may publish twin/**
#   viewer.pem    viewer.key        CN viewer: valid, may only subscribe
#   wrong-ca.pem  wrong-ca.key      CN daemon, signed by another CA (wrong-ca-root.pem): refused
#   expired.pem   expired.key       CN daemon, by the cell's CA, valid 2020-01-01..2020-01-02: refused
set -eu
dir=${1:?usage: make-test-pki.sh DIR [ROUTER_SAN]}
san=${2:-DNS:localhost,IP:127.0.0.1}
if [ -e "$dir" ]; then
    echo "make-test-pki.sh: $dir exists; give a new directory" >&2
    exit 2
fi
command -v openssl >/dev/null || { echo "make-test-pki.sh: openssl not found" >&2; exit 2; }
mkdir -p "$dir"
umask 077
cd "$dir"
days=825

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1.key" 2>/dev/null; }

ca() {  # ca NAME CN
    key "$1"
    openssl req -new -x509 -key "$1.key" -out "$1.pem" -days "$days" -subj "/O=grating-twin test/CN=$2" \
        -addext "basicConstraints=critical,CA:TRUE" \
        -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
}

leaf() {  # leaf NAME CN CA_NAME EXT_FILE
    key "$1"
    openssl req -new -key "$1.key" -out "$1.csr" -subj "/O=grating-twin test/CN=$2" 2>/dev/null
    openssl x509 -req -in "$1.csr" -CA "$3.pem" -CAkey "$3.key" -set_serial "0x$(openssl rand -hex 8)" \
        -days "$days" -extfile "$4" -out "$1.pem" 2>/dev/null
    rm -f "$1.csr"
}

printf 'basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\nsubjectAltName=%s\n' "$san" >server.ext
printf 'basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage=clientAuth\n' >client.ext

ca ca "grating-twin test CA"
leaf router router ca server.ext
shift $(($# < 2 ? $# : 2))
for who in daemon twin viewer "$@"; do
    case $who in *[!A-Za-z0-9_.-]*|'') echo "make-test-pki.sh: bad CN '$who'" >&2; exit 2;; esac
    leaf "$who" "$who" ca client.ext
done
ca wrong-ca-root "another CA"
leaf wrong-ca daemon wrong-ca-root client.ext

# expired: `openssl ca` takes explicit start and end dates (x509 -req cannot backdate)
mkdir -p expired.db
: >expired.db/index.txt
echo 01 >expired.db/serial
cat >expired.db/ca.cnf <<CNF
[ca]
default_ca = test
[test]
database = expired.db/index.txt
serial = expired.db/serial
new_certs_dir = expired.db
default_md = sha256
policy = any
copy_extensions = none
[any]
commonName = supplied
organizationName = optional
[ext]
basicConstraints = critical,CA:FALSE
keyUsage = critical,digitalSignature
extendedKeyUsage = clientAuth
CNF
key expired
openssl req -new -key expired.key -out expired.csr -subj "/O=grating-twin test/CN=daemon" 2>/dev/null
openssl ca -batch -config expired.db/ca.cnf -cert ca.pem -keyfile ca.key -in expired.csr \
    -startdate 20200101000000Z -enddate 20200102000000Z -extensions ext -notext -out expired.pem 2>/dev/null
rm -rf expired.db expired.csr server.ext client.ext wrong-ca-root.key ca.srl
chmod 644 ./*.pem
echo "make-test-pki.sh: wrote $(ls | tr '\n' ' ')in $dir"
