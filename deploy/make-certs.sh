#!/bin/sh
# Make the secrets of a vergence cluster with openssl: a CA, the router's certificate, one client
# certificate per role (its common name is the role: the router's ACL can match it), a password
# dictionary with a random password per role, and one Zenoh client config per role.
#
#   deploy/make-certs.sh [-o OUT_DIR] [-r ROLE,...] [-d DAYS] [ROUTER_NAME_OR_IP ...]
#
# OUT_DIR defaults to deploy/secrets (git-ignored). Every ROUTER_NAME_OR_IP goes into the router
# certificate's subjectAltName: clients verify the name they connect to (verify_name_on_connect), so list
# every host name and address clients use to reach the router. Default: router localhost 127.0.0.1.
# Writes, in OUT_DIR:
#   ca.pem ca-key.pem                 the CA (keep ca-key.pem off the cluster)
#   router.pem router-key.pem         the router's certificate (CN=router)
#   <role>.pem <role>-key.pem         a client certificate per role (CN=<role>)
#   users.txt                         <role>:<password> per line: the router's usrpwd dictionary_file
#   clients/<role>-tls.json5          a client config per role: tls + mutual TLS + user/password
#   clients/<role>-tcp.json5          the same over plain tcp (user/password only), for a private network
# Existing files are kept (delete OUT_DIR to start over); the paths inside the configs are
# SECRETS_DIR (default /etc/vergence/secrets, where docker-compose.yml mounts OUT_DIR).
set -eu

OUT=deploy/secrets
ROLES=capture,worker,reducer,actuator,monitor,record,replay,fixate,ros2
DAYS=825
SECRETS_DIR=${SECRETS_DIR:-/etc/vergence/secrets}
ROUTER_PORT=${ROUTER_PORT:-7447}
while getopts o:r:d:h opt; do
    case $opt in
        o) OUT=$OPTARG ;;
        r) ROLES=$OPTARG ;;
        d) DAYS=$OPTARG ;;
        *) sed -n '2,20p' "$0"; exit 2 ;;
    esac
done
shift $((OPTIND - 1))
[ $# -gt 0 ] || set -- router localhost 127.0.0.1
ROUTER_HOST=$1

if ! command -v openssl >/dev/null; then
    echo "make-certs.sh: openssl not found: install it (apt-get install openssl)" >&2
    exit 1
fi
mkdir -p "$OUT/clients"
umask 077

san=""
for name in "$@"; do
    if printf '%s' "$name" | grep -Eq '^[0-9.]+$|:'; then kind=IP; else kind=DNS; fi
    san="${san:+$san,}$kind:$name"
done

key() {  # an EC P-256 key in PKCS#8, which rustls (Zenoh's TLS) reads
    [ -f "$1" ] || openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null
}

if [ ! -f "$OUT/ca.pem" ]; then
    key "$OUT/ca-key.pem"
    openssl req -x509 -new -key "$OUT/ca-key.pem" -sha256 -days "$DAYS" -subj "/CN=vergence-ca" \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -out "$OUT/ca.pem"
fi

leaf() {  # leaf NAME EXTENDED_KEY_USAGE [SUBJECT_ALT_NAME]
    [ -f "$OUT/$1.pem" ] && return 0
    key "$OUT/$1-key.pem"
    ext="$OUT/$1.ext"
    {
        echo "basicConstraints=critical,CA:FALSE"
        echo "keyUsage=critical,digitalSignature,keyEncipherment"
        echo "extendedKeyUsage=$2"
        if [ -n "${3:-}" ]; then echo "subjectAltName=$3"; fi
    } >"$ext"
    openssl req -new -key "$OUT/$1-key.pem" -subj "/CN=$1" -out "$OUT/$1.csr"
    openssl x509 -req -in "$OUT/$1.csr" -CA "$OUT/ca.pem" -CAkey "$OUT/ca-key.pem" -CAcreateserial \
        -days "$DAYS" -sha256 -extfile "$ext" -out "$OUT/$1.pem" 2>/dev/null
    rm -f "$OUT/$1.csr" "$ext"
}

leaf router serverAuth,clientAuth "$san"

touch "$OUT/users.txt"
for role in $(echo "$ROLES" | tr , ' '); do
    leaf "$role" clientAuth "DNS:$role"
    if ! grep -q "^$role:" "$OUT/users.txt"; then
        echo "$role:$(openssl rand -hex 16)" >>"$OUT/users.txt"
    fi
    password=$(grep "^$role:" "$OUT/users.txt" | head -n1 | cut -d: -f2-)
    for variant in tls tcp; do
        file="$OUT/clients/$role-$variant.json5"
        {
            echo "// vergence $role: a Zenoh client of the cluster router ($variant), made by make-certs.sh"
            echo "{"
            echo "  mode: \"client\","
            echo "  // retry forever, every 0.1-0.5 s: back within 0.5 s of a router restart"
            echo "  connect: { endpoints: [\"$variant/$ROUTER_HOST:$ROUTER_PORT\"], timeout_ms: -1,"
            echo "             retry: { period_init_ms: 100, period_max_ms: 500,"
            echo "                      period_increase_factor: 2 } },"
            echo "  scouting: { multicast: { enabled: false }, gossip: { enabled: false } },"
            echo "  transport: {"
            echo "    link: {"
            echo "      tx: { lease: 1000, keep_alive: 4 },"
            if [ $variant = tls ]; then
                echo "      tls: {"
                echo "        root_ca_certificate: \"$SECRETS_DIR/ca.pem\","
                echo "        connect_certificate: \"$SECRETS_DIR/$role.pem\","
                echo "        connect_private_key: \"$SECRETS_DIR/$role-key.pem\","
                echo "        enable_mtls: true,"
                echo "        verify_name_on_connect: true,"
                echo "      },"
            fi
            echo "    },"
            echo "    auth: { usrpwd: { user: \"$role\", password: \"$password\" } },"
            echo "  },"
            echo "}"
        } >"$file"
    done
done
rm -f "$OUT/ca.srl"
echo "make-certs.sh: wrote $OUT (router names: $*; roles: $ROLES)"
