"""measurement_sets: instrument (noise preset), limits mode and the out-of-limit extent accepted with limits=warn

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-23 06:00:00
"""
from alembic import op
import sqlalchemy as sa


revision = '0003'
down_revision = '0002'
branch_labels = None
depends_on = None


def upgrade() -> None:
    # all nullable, no default: existing sets read as "no instrument given" and "reject", as they were parsed
    with op.batch_alter_table('measurement_sets', schema=None) as batch_op:
        batch_op.add_column(sa.Column('instrument', sa.String(length=32), nullable=True))
        batch_op.add_column(sa.Column('limits', sa.String(length=16), nullable=True))
        batch_op.add_column(sa.Column('out_of_limits', sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('measurement_sets', schema=None) as batch_op:
        batch_op.drop_column('out_of_limits')
        batch_op.drop_column('limits')
        batch_op.drop_column('instrument')
